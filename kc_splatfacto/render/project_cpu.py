"""Projection and SH colours in one compiled pass (numba), differentiable: the "cpu" backend's per-Gaussian stage.

Same outputs and gradients as the torch reference (``projection.fully_fused_projection`` followed by
``sh.sh_to_rgb`` with the visibility mask, ``opacities * compensations`` in antialiased mode), which stays the test
oracle. Gradients flow to means, quats, scales, opacities, SH coefficients and viewmats (through the camera rotation
and translation, and through ``campos``, the camera centres the caller computes from the viewmats with torch so that
autograd differentiates the inverse); ``Ks`` get none, as in gsplat. Kernels: ``_project_kernels.py``.

NaN/inf in means, quats, scales, opacities or SH coefficients are found by the forward kernel while it reads them
(no separate pass over the tensors) and raise :class:`NonFiniteInputError`.
"""

from __future__ import annotations

from typing import Callable, Optional, Union

import numpy as np
import torch
from torch import Tensor

from . import _project_kernels as PK
from .constants import (
    ALPHA_THRESHOLD,
    EXTENT_SIGMA,
    FOV_CLAMP_MARGIN,
    SH_C0,
    SH_C1,
    SH_C2,
    SH_C3,
    SH_COLOR_OFFSET,
)
from .non_finite import NonFiniteInputError, non_finite_message
from .projection import RADIUS_MAX, ProjectedSplats
from .sh import SplitSH

__all__ = ["ProjectedSplats", "project_and_shade_cpu"]

_SH_CONSTS = np.array((SH_C0, SH_C1) + tuple(SH_C2) + tuple(SH_C3), np.float64)
assert _SH_CONSTS.shape == (PK.N_SH_CONSTS,)
# the reference compares float32 opacities with the threshold rounded to float32
_ALPHA_THRESHOLD_F32 = float(np.float32(ALPHA_THRESHOLD))


def _np(t: Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


def _params(width: int, height: int, eps2d: float, near_plane: float, far_plane: float, radius_clip: float):
    params = np.empty(PK.N_PARAMS, np.float64)
    params[PK.P_WIDTH] = width
    params[PK.P_HEIGHT] = height
    params[PK.P_EPS2D] = eps2d
    params[PK.P_NEAR] = near_plane
    params[PK.P_FAR] = far_plane
    params[PK.P_RADIUS_CLIP] = radius_clip
    params[PK.P_ALPHA_THRESHOLD] = _ALPHA_THRESHOLD_F32
    params[PK.P_EXTENT_SIGMA] = EXTENT_SIGMA
    params[PK.P_FOV_MARGIN] = FOV_CLAMP_MARGIN
    params[PK.P_RADIUS_MAX] = RADIUS_MAX
    params[PK.P_COLOR_OFFSET] = SH_COLOR_OFFSET
    return params


_BAD_FIELDS = (
    (PK.BAD_MEANS, "means"), (PK.BAD_QUATS, "quats"), (PK.BAD_SCALES, "scales"),
    (PK.BAD_OPACITIES, "opacities"), (PK.BAD_COLORS, "colors"),
)


def _raise_non_finite(bad: np.ndarray, tensors: dict[str, Callable[[], Tensor]]) -> None:
    """Raise for the fields flagged in ``bad``; ``tensors`` maps each field to a function giving its values (only
    called on this error path)."""
    flags = int(np.bitwise_or.reduce(bad)) if bad.size else 0
    names = tuple(name for bit, name in _BAD_FIELDS if flags & bit)
    if names:
        raise NonFiniteInputError(non_finite_message(names[0], tensors[names[0]]()), names)


class _ProjectAndShade(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, sh_dc, sh_rest, viewmats, campos, Ks, settings):
        width, height, eps2d, near_plane, far_plane, radius_clip, antialiased, sh_degree = settings
        n_cams, n_gauss = viewmats.shape[0], means.shape[0]
        dtype = means.dtype
        np_dtype = np.float64 if dtype == torch.float64 else np.float32
        arrays = [_np(means), _np(quats), _np(scales), _np(opacities)]
        if sh_degree >= 0:
            sh_dc_np = _np(sh_dc if sh_dc.dim() == 4 else sh_dc[None])
            sh_rest_np = _np(sh_rest if sh_rest.dim() == 4 else sh_rest[None])
        else:
            sh_dc_np = sh_rest_np = np.zeros((1, 0, 0, 3), np_dtype)
        cams = [np.ascontiguousarray(t.detach().to(torch.float64).numpy()) for t in (viewmats, Ks, campos)]
        for name, arr in zip(("viewmats", "Ks"), cams[:2]):
            if not np.isfinite(arr).all():
                raise NonFiniteInputError(non_finite_message(name, viewmats if name == "viewmats" else Ks), (name,))
        params = _params(width, height, eps2d, near_plane, far_plane, radius_clip)
        radii = np.empty((n_cams, n_gauss, 2), np.int32)
        means2d = np.empty((n_cams, n_gauss, 2), np_dtype)
        depths = np.empty((n_cams, n_gauss), np_dtype)
        conics = np.empty((n_cams, n_gauss, 3), np_dtype)
        comps = np.empty((n_cams, n_gauss), np_dtype)
        opacities_c = np.empty((n_cams, n_gauss), np_dtype)
        colors = np.empty((n_cams, n_gauss if sh_degree >= 0 else 0, 3), np_dtype)
        bad = np.empty(n_gauss, np.uint8)
        PK.project_sh_fwd(*arrays, sh_dc_np, sh_rest_np, *cams, params, _SH_CONSTS, antialiased, sh_degree,
                          radii, means2d, depths, conics, comps, opacities_c, colors, bad)
        _raise_non_finite(bad, {
            "means": lambda: means, "quats": lambda: quats, "scales": lambda: scales, "opacities": lambda: opacities,
            "colors": lambda: torch.cat([sh_dc.detach().reshape(-1), sh_rest.detach().reshape(-1)]),
        })
        ctx.settings = settings
        ctx.arrays = (arrays, sh_dc_np, sh_rest_np, cams, params, radii)
        ctx.sh_shapes = (tuple(sh_dc.shape), tuple(sh_rest.shape)) if sh_degree >= 0 else None
        radii_t = torch.from_numpy(radii)
        ctx.mark_non_differentiable(radii_t)
        colors_t = torch.from_numpy(colors)
        return (radii_t, torch.from_numpy(means2d), torch.from_numpy(depths), torch.from_numpy(conics),
                torch.from_numpy(opacities_c), colors_t)

    @staticmethod
    def backward(ctx, _v_radii, v_means2d, v_depths, v_conics, v_opacities_c, v_colors):
        width, height, eps2d, near_plane, far_plane, radius_clip, antialiased, sh_degree = ctx.settings
        arrays, sh_dc_np, sh_rest_np, cams, params, radii = ctx.arrays
        n_cams, n_gauss = radii.shape[:2]
        np_dtype = arrays[0].dtype

        def upstream(v, shape):
            return np.zeros(shape, np_dtype) if v is None else _np(v.to(torch.float64 if np_dtype == np.float64
                                                                        else torch.float32))

        v_m2d = upstream(v_means2d, (n_cams, n_gauss, 2))
        v_dep = upstream(v_depths, (n_cams, n_gauss))
        v_con = upstream(v_conics, (n_cams, n_gauss, 3))
        v_opc = upstream(v_opacities_c, (n_cams, n_gauss))
        v_col = upstream(v_colors, (n_cams, n_gauss, 3) if sh_degree >= 0 else (n_cams, 0, 3))
        want_camera = bool(ctx.needs_input_grad[6] or ctx.needs_input_grad[7])
        v_means = np.empty((n_gauss, 3), np_dtype)
        v_quats = np.empty((n_gauss, 4), np_dtype)
        v_scales = np.empty((n_gauss, 3), np_dtype)
        v_opac = np.empty(n_gauss, np_dtype)
        v_sh_dc = np.empty(sh_dc_np.shape, np_dtype)
        v_sh_rest = np.empty(sh_rest_np.shape, np_dtype)
        parts_shape = (n_cams, n_gauss) if want_camera else (0, 0)
        v_view_parts = np.zeros(parts_shape + (12,), np.float64)
        v_campos_parts = np.zeros(parts_shape + (3,), np.float64)
        PK.project_sh_bwd(*arrays, sh_dc_np, sh_rest_np, *cams, params, _SH_CONSTS, antialiased, sh_degree, radii,
                          v_m2d, v_dep, v_con, v_opc, v_col, want_camera,
                          v_means, v_quats, v_scales, v_opac, v_sh_dc, v_sh_rest, v_view_parts, v_campos_parts)
        dtype = torch.float64 if np_dtype == np.float64 else torch.float32
        v_sh_dc_t = v_sh_rest_t = None
        if sh_degree >= 0:
            dc_shape, rest_shape = ctx.sh_shapes
            if ctx.needs_input_grad[4]:
                v_sh_dc_t = torch.from_numpy(v_sh_dc).reshape(dc_shape)
            if ctx.needs_input_grad[5]:
                v_sh_rest_t = torch.from_numpy(v_sh_rest).reshape(rest_shape)
        v_viewmats = v_campos = None
        if want_camera:
            parts = v_view_parts.sum(axis=1)  # [C, 12], a fixed-order float64 sum
            v_viewmats = torch.zeros(n_cams, 4, 4, dtype=torch.float64)
            v_viewmats[:, :3, :3] = torch.from_numpy(parts[:, :9]).reshape(n_cams, 3, 3)
            v_viewmats[:, :3, 3] = torch.from_numpy(parts[:, 9:])
            v_viewmats = v_viewmats.to(dtype)
            v_campos = torch.from_numpy(v_campos_parts.sum(axis=1)).to(dtype)
        return (torch.from_numpy(v_means), torch.from_numpy(v_quats), torch.from_numpy(v_scales),
                torch.from_numpy(v_opac), v_sh_dc_t, v_sh_rest_t, v_viewmats, v_campos, None, None)


def project_and_shade_cpu(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    shs: Union[Tensor, SplitSH, None],
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: Optional[int],
    eps2d: float,
    near_plane: float,
    far_plane: float,
    radius_clip: float,
    antialiased: bool,
) -> ProjectedSplats:
    """Project N Gaussians into C cameras and evaluate their SH colours, in one compiled pass.

    Args:
        means [N, 3], quats [N, 4] wxyz (any norm), scales [N, 3] linear, opacities [N]: float32 or float64 CPU
            tensors (outputs and gradients in that dtype; the arithmetic is float64).
        shs: SH coefficients [N, K, 3] or [C, N, K, 3], or a :class:`SplitSH` of them (read in place, no
            concatenated copy), when ``sh_degree`` is not None (else ignored).
        viewmats [C, 4, 4] world-to-camera, Ks [C, 3, 3]; width, height in pixels.

    Returns:
        :class:`ProjectedSplats`.

    Raises:
        NonFiniteInputError: an input holds NaN/inf (the first such argument is named, with its count).
    """
    degree = -1 if sh_degree is None else int(sh_degree)
    dtype = means.dtype
    if shs is None or degree < 0:
        sh_dc = sh_rest = means.new_zeros((0, 0, 3))
    elif isinstance(shs, SplitSH):
        shs.check()
        sh_dc, sh_rest = shs.dc.to(dtype), shs.rest.to(dtype)
    else:
        sh_dc, sh_rest = shs[..., :1, :].to(dtype), shs[..., 1:, :].to(dtype)
    # camera centres from the inverse, differentiated by autograd as the reference's torch.linalg.inv
    campos = torch.linalg.inv(viewmats)[:, :3, 3] if degree >= 0 else viewmats.new_zeros(viewmats.shape[0], 3)
    settings = (int(width), int(height), float(eps2d), float(near_plane), float(far_plane), float(radius_clip),
                bool(antialiased), degree)
    radii, means2d, depths, conics, opacities_c, colors = _ProjectAndShade.apply(
        means, quats.to(dtype), scales.to(dtype), opacities.to(dtype), sh_dc, sh_rest, viewmats, campos, Ks, settings
    )
    return ProjectedSplats(radii, means2d, depths, conics, opacities_c, colors if degree >= 0 else None)
