"""Real spherical harmonics up to degree 3, with gsplat 1.5.3's basis constants and sign conventions."""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from .constants import SH_C0, SH_C1, SH_C2, SH_C3, SH_COLOR_OFFSET, SH_MAX_DEGREE


class SplitSH(NamedTuple):
    """SH coefficients held in two tensors, as Splatfacto holds them: ``dc`` [..., N, 1, 3] (degree 0) and ``rest``
    [..., N, K - 1, 3]. ``rasterization(colors=SplitSH(...), sh_degree=d)`` means ``colors=split.cat()``; the compiled
    CPU path reads and differentiates the two tensors in place, so a step makes no concatenated [N, K, 3] copy and
    no sliced copies of its gradient."""

    dc: Tensor
    rest: Tensor

    @property
    def shape(self) -> torch.Size:
        """The shape of :meth:`cat`'s result."""
        return self.rest.shape[:-2] + (1 + self.rest.shape[-2], self.rest.shape[-1])

    def cat(self) -> Tensor:
        """[..., N, K, 3]: the coefficients in one tensor (gsplat's and the torch reference's input)."""
        return torch.cat([self.dc, self.rest], dim=-2)

    def check(self) -> None:
        """Raise ValueError unless ``dc`` is [..., N, 1, 3] and ``rest`` [..., N, K - 1, 3] with the same leading shape."""
        dc, rest = self.dc, self.rest
        if dc.dim() < 3 or dc.shape[-2] != 1 or rest.dim() != dc.dim() or rest.shape[:-2] != dc.shape[:-2] \
                or rest.shape[-1] != dc.shape[-1]:
            raise ValueError(
                f"SplitSH needs dc [..., N, 1, 3] and rest [..., N, K - 1, 3] with the same leading shape, got "
                f"dc {tuple(dc.shape)} and rest {tuple(rest.shape)}"
            )


def num_sh_bases(degree: int) -> int:
    """Number of SH coefficients of a degree: (degree + 1)^2."""
    return (degree + 1) ** 2


def sh_bases(degree: int, dirs: Tensor) -> Tensor:
    """SH basis functions at unit directions, in gsplat's order and signs (Sloan 2013).

    Args:
        degree: 0..3.
        dirs: [..., 3] unit directions (x, y, z).

    Returns:
        [..., (degree + 1)^2] basis values.
    """
    if not 0 <= degree <= SH_MAX_DEGREE:
        raise ValueError(f"sh_degree must be in 0..{SH_MAX_DEGREE}, got {degree}")
    x, y, z = torch.unbind(dirs, dim=-1)
    bases = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        bases += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xy_c, zz_c, const_c, xx_yy_c = SH_C2
        z2 = z * z
        fc1 = x * x - y * y
        fs1 = 2 * x * y
        bases += [
            xx_yy_c * fs1,  # 0.5463 * 2xy
            -xy_c * z * y,
            zz_c * z2 - const_c,
            -xy_c * z * x,
            xx_yy_c * fc1,
        ]
    if degree >= 3:
        c3_3, c3_2, c3_1z, c3_1c, c3_0z3, c3_0z = SH_C3
        fc2 = x * fc1 - y * fs1
        fs2 = x * fs1 + y * fc1
        tmp_c = -c3_1z * z2 + c3_1c
        bases += [
            -c3_3 * fs2,
            c3_2 * z * fs1,
            tmp_c * y,
            z * (c3_0z3 * z2 - c3_0z),
            tmp_c * x,
            c3_2 * z * fc1,
            -c3_3 * fc2,
        ]
    return torch.stack(bases, dim=-1)


def spherical_harmonics(
    degree: int, dirs: Tensor, coeffs: Tensor, masks: Optional[Tensor] = None
) -> Tensor:
    """Evaluate SH colours (gsplat's ``spherical_harmonics``): sum_k basis_k(dir / |dir|) * coeffs_k.

    Args:
        degree: active degree (0..3); only the first (degree + 1)^2 coefficients are used.
        dirs: [..., 3] directions, any length (normalized here; a zero direction gives the degree-0 term only).
        coeffs: [..., K, 3] with K >= (degree + 1)^2.
        masks: [...] bool; False entries give colour 0 (gsplat skips culled Gaussians).

    Returns:
        [..., 3] colours, before the +0.5 offset.
    """
    k = num_sh_bases(degree)
    if coeffs.shape[-2] < k:
        raise ValueError(f"sh_degree={degree} needs {k} SH coefficients per Gaussian, got {coeffs.shape[-2]}")
    bases = sh_bases(degree, F.normalize(dirs, p=2, dim=-1))  # [..., k]
    colors = (bases[..., None] * coeffs[..., :k, :]).sum(dim=-2)
    if masks is not None:
        colors = torch.where(masks[..., None], colors, torch.zeros_like(colors))
    return colors


def sh_to_rgb(degree: int, dirs: Tensor, coeffs: Tensor, masks: Optional[Tensor] = None) -> Tensor:
    """Colours as gsplat's ``rasterization`` uses them: ``max(SH(dir) + 0.5, 0)``. Shapes as :func:`spherical_harmonics`."""
    return torch.clamp_min(spherical_harmonics(degree, dirs, coeffs, masks) + SH_COLOR_OFFSET, 0.0)
