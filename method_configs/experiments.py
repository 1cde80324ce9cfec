"""Method specifications under study, not registered: a study names them at run time through the registry's
environment variable (see :mod:`kc_splatfacto.registry`), e.g.::

    KC_SPLATFACTO_METHOD_CONFIGS="splatfacto-sparse-sh=method_configs.experiments:splatfacto_sparse_sh,\\
    kc-splatfacto-sparse-sh=method_configs.experiments:kc_splatfacto_sparse_sh" kc-bench --methods ...

A variant moves to ``pyproject.toml``'s entry points once a paired study shows it helps (an interval that excludes
zero); until then it stays here with the study that tried it named below.

``*-sparse-sh``: the SH degree follows the number of training views, at least two views per SH coefficient
(``sh_views_per_coefficient=2``: degree 1 on the 12-view scenes, 0 (plain RGB) on entry-P10's 5 views, Splatfacto's 3
from 32 views on). Splatfacto's 30k castle-P30 collapse came from view-dependent colour fitted to 12 views
(docs/results/castle-P30-30k); docs/results/sparse-sh-7k is the paired study of this variant.
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
