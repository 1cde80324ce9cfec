"""Method specifications under study, not registered: a study names them at run time through the registry's
environment variable (see :mod:`kc_splatfacto.registry`), e.g.::

    KC_SPLATFACTO_METHOD_CONFIGS="splatfacto-sparse-sh=method_configs.experiments:splatfacto_sparse_sh,\\
    kc-splatfacto-sparse-sh=method_configs.experiments:kc_splatfacto_sparse_sh" kc-bench --methods ...

A variant moves to ``pyproject.toml``'s entry points once a paired study shows it helps (an interval that excludes
zero).

``*-sparse-sh``: the SH degree follows the number of training views, at least two views per SH coefficient
(``sh_views_per_coefficient=2``: degree 1 on 12 views, 0 (plain RGB) on 5, Splatfacto's 3 from 32 views on), because a
degree-3 colour has more unknowns per channel than a sparse scene has views of a Gaussian and can over-fit
view-dependent colour.
"""

from __future__ import annotations

from kc_splatfacto.registry import MethodSpecification
from method_configs.splatfacto_configs import PAPER, _trainer

SPARSE_SH_VIEWS_PER_COEFFICIENT = 2.0
"""views per SH coefficient the sparse-SH variants ask for"""

splatfacto_sparse_sh = MethodSpecification(
    config=_trainer("splatfacto-sparse-sh", sh_views_per_coefficient=SPARSE_SH_VIEWS_PER_COEFFICIENT),
    description="Splatfacto with the SH degree capped by the training views (>= 2 views per SH coefficient)",
)
kc_splatfacto_sparse_sh = MethodSpecification(
    config=_trainer("kc-splatfacto-sparse-sh", PAPER, sh_views_per_coefficient=SPARSE_SH_VIEWS_PER_COEFFICIENT),
    description="KC-3DGS (paper settings) with the SH degree capped by the training views (>= 2 views per SH coefficient)",
)
