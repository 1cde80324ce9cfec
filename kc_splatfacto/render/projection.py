"""EWA projection of 3D Gaussians to screen space, as gsplat 1.5.3's ``fully_fused_projection`` (pinhole, unpacked).

Every function is plain differentiable torch: autograd provides the backward. Culled (camera, Gaussian) pairs get
radii 0 and zeros in every other output, with zero gradient, as gsplat's kernels leave them.
"""

from __future__ import annotations

from typing import NamedTuple, Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from .constants import ALPHA_THRESHOLD, EPS2D, EXTENT_SIGMA, FAR_PLANE, FOV_CLAMP_MARGIN, NEAR_PLANE


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices from quaternions, normalized here.

    Args:
        quats: [..., 4] wxyz, any norm. A zero quaternion gives the identity (no NaN, zero gradient), where
            gsplat's ``rsqrt`` would give NaN.

    Returns:
        [..., 3, 3] rotation matrices.
    """
    w, x, y, z = torch.unbind(F.normalize(quats, p=2, dim=-1), dim=-1)
    rotmat = torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    )
    return rotmat.reshape(quats.shape[:-1] + (3, 3))


def rotmat_to_quat(rotmats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [N,3,3] -> unit quaternions [N,4] (w, x, y, z) with w >= 0 (Shepperd's method), float64;
    the inverse of :func:`quat_to_rotmat` (camera paths, the demo scene's COLMAP model)."""
    if rotmats.ndim != 3 or rotmats.shape[1:] != (3, 3):
        raise ValueError(f"rotmat_to_quat: expected [N,3,3], got {tuple(rotmats.shape)}")
    r = rotmats.to(torch.float64)
    m00, m11, m22 = r[:, 0, 0], r[:, 1, 1], r[:, 2, 2]
    # Four candidate (unnormalized) quaternions; use the one with the largest diagonal term for stability.
    candidates = torch.stack(
        [
            torch.stack([1 + m00 + m11 + m22, r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], -1),
            torch.stack([r[:, 2, 1] - r[:, 1, 2], 1 + m00 - m11 - m22, r[:, 0, 1] + r[:, 1, 0], r[:, 0, 2] + r[:, 2, 0]], -1),
            torch.stack([r[:, 0, 2] - r[:, 2, 0], r[:, 0, 1] + r[:, 1, 0], 1 - m00 + m11 - m22, r[:, 1, 2] + r[:, 2, 1]], -1),
            torch.stack([r[:, 1, 0] - r[:, 0, 1], r[:, 0, 2] + r[:, 2, 0], r[:, 1, 2] + r[:, 2, 1], 1 - m00 - m11 + m22], -1),
        ],
        dim=1,
    )  # [N, 4 candidates, 4]
    choice = torch.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], -1).argmax(-1)
    q = candidates[torch.arange(r.shape[0]), choice]
    # the norm written out: a reduction's order (and so its last bit) follows the CPU's vector width
    q = q / torch.sqrt(q[:, 0:1] * q[:, 0:1] + q[:, 1:2] * q[:, 1:2] + q[:, 2:3] * q[:, 2:3] + q[:, 3:4] * q[:, 3:4])
    return torch.where(q[:, :1] < 0, -q, q)


def quat_scale_to_covar_half(quats: Tensor, scales: Tensor) -> Tensor:
    """Covariance factors ``M = R S``, so that the world covariance is ``M M^T``.

    Carrying the factor instead of the covariance keeps every projected covariance positive semi-definite by
    construction and turns the per-Gaussian 3x3 products into one camera-rotation GEMM plus elementwise ops.

    Args:
        quats: [N, 4] wxyz (normalized inside).
        scales: [N, 3] linear standard deviations along the local axes.

    Returns:
        [N, 3, 3] factors (column k = local axis k scaled by scale k).
    """
    return quat_to_rotmat(quats) * scales[..., None, :]


def world_to_cam(means: Tensor, covar_halves: Tensor, viewmats: Tensor) -> tuple[Tensor, Tensor]:
    """Means and covariance factors in camera space: ``mu_c = W mu + t``, ``M_c = W M`` (``Sigma_c = M_c M_c^T``).

    Args:
        means: [N, 3] world positions.
        covar_halves: [N, 3, 3] world covariance factors from :func:`quat_scale_to_covar_half`.
        viewmats: [C, 4, 4] world-to-camera (OpenCV axes: x right, y down, z forward).

    Returns:
        means_c [C, N, 3] and covar_halves_c [C, N, 3, 3].
    """
    rot = viewmats[:, :3, :3]  # [C, 3, 3]
    trans = viewmats[:, :3, 3]  # [C, 3]
    means_c = torch.einsum("cij,nj->cni", rot, means) + trans[:, None, :]
    halves_c = torch.einsum("cij,njk->cnik", rot, covar_halves)
    return means_c, halves_c


def persp_proj(
    means_c: Tensor, covar_halves_c: Tensor, Ks: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """Pinhole projection of means and the EWA (first-order) projection of covariances, ``J Sigma_c J^T``.

    The Jacobian is evaluated at x/z, y/z clamped to the image's extent plus ``FOV_CLAMP_MARGIN * tan(fov/2)`` on each
    side (gsplat's ``persp_proj``), so Gaussians far outside the frustum keep a bounded footprint. The mean itself is
    not clamped. With ``Sigma_c = M_c M_c^T``, ``J Sigma_c J^T = (J M_c)(J M_c)^T`` and ``J`` has two non-zero entries
    per row, so the rows of ``J M_c`` are elementwise combinations of the rows of ``M_c``.

    Args:
        means_c: [C, N, 3] camera-space means with z > 0 (callers replace invalid depths first).
        covar_halves_c: [C, N, 3, 3] camera-space covariance factors.
        Ks: [C, 3, 3] intrinsics.
        width, height: image size in pixels.

    Returns:
        means2d [C, N, 2] in pixels and covars2d [C, N, 3] as (xx, xy, yy), before the eps2d dilation.
    """
    x, y, z = torch.unbind(means_c, dim=-1)  # [C, N]
    fx = Ks[:, 0, 0, None]
    fy = Ks[:, 1, 1, None]
    cx = Ks[:, 0, 2, None]
    cy = Ks[:, 1, 2, None]
    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + FOV_CLAMP_MARGIN * tan_fovx
    lim_x_neg = cx / fx + FOV_CLAMP_MARGIN * tan_fovx
    lim_y_pos = (height - cy) / fy + FOV_CLAMP_MARGIN * tan_fovy
    lim_y_neg = cy / fy + FOV_CLAMP_MARGIN * tan_fovy
    rz = 1.0 / z
    tx = z * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x * rz))
    ty = z * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y * rz))
    # J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]; rows of J M_c:
    row_z = covar_halves_c[..., 2, :]  # [C, N, 3]
    jm_x = (fx * rz)[..., None] * covar_halves_c[..., 0, :] - (fx * tx * rz * rz)[..., None] * row_z
    jm_y = (fy * rz)[..., None] * covar_halves_c[..., 1, :] - (fy * ty * rz * rz)[..., None] * row_z
    covars2d = torch.stack([(jm_x * jm_x).sum(-1), (jm_x * jm_y).sum(-1), (jm_y * jm_y).sum(-1)], dim=-1)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)
    return means2d, covars2d


# Largest radius stored (pixels); any radius this large already covers every tile of any image.
RADIUS_MAX = 2**30


class Projection(NamedTuple):
    """Outputs of :func:`fully_fused_projection`; entries of culled pairs are 0."""

    radii: Tensor  # [C, N, 2] int32, per-axis pixel radii; 0 = culled
    means2d: Tensor  # [C, N, 2]
    depths: Tensor  # [C, N] camera-space z
    conics: Tensor  # [C, N, 3] upper triangle (a, b, c) of the inverse dilated 2D covariance
    compensations: Optional[Tensor]  # [C, N] antialiasing opacity factor, or None


class ProjectedSplats(NamedTuple):
    """Per (camera, Gaussian) inputs of the compositing, from the compiled projection (``project_cpu``) or the torch
    one; culled pairs have radii 0 and zeros elsewhere (SH colour ``max(0.5, 0)``)."""

    radii: Tensor  # [C, N, 2] int32
    means2d: Tensor  # [C, N, 2]
    depths: Tensor  # [C, N]
    conics: Tensor  # [C, N, 3]
    opacities: Tensor  # [C, N] opacity (times the compensation in antialiased mode)
    colors: Optional[Tensor]  # [C, N, D]: max(SH + 0.5, 0) (D = 3), or None from project_cpu without SH


def fully_fused_projection(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    opacities: Optional[Tensor] = None,
    eps2d: float = EPS2D,
    near_plane: float = NEAR_PLANE,
    far_plane: float = FAR_PLANE,
    radius_clip: float = 0.0,
    calc_compensations: bool = False,
) -> Projection:
    """Project Gaussians into C pinhole cameras, with gsplat 1.5.3's culling and radii.

    Steps (all per camera and Gaussian):
    ``covar = R S S^T R^T``; camera space; cull unless ``near_plane <= z <= far_plane``; ``cov2d = J W covar W^T J^T``;
    dilate ``cov2d += eps2d * I`` (compensation ``sqrt(max(0, det_orig / det_blur))`` when asked); cull when the dilated
    determinant is <= 0; conic = inverse; when ``opacities`` are given, cull ``opacity (* compensation) < 1/255`` and
    tighten the extent to ``min(3.33, sqrt(2 log(opacity / (1/255))))`` standard deviations; radii
    ``ceil(extent * sqrt(cov2d_xx))``, ``ceil(extent * sqrt(cov2d_yy))``; cull when both are <= ``radius_clip`` or the
    box lies outside the image.

    Args:
        means: [N, 3]; quats: [N, 4] wxyz (any norm); scales: [N, 3] linear.
        viewmats: [C, 4, 4] world-to-camera; Ks: [C, 3, 3].
        width, height: image size.
        opacities: [N] in [0, 1] for the opacity-aware extent and culling (gsplat passes them), or None.
        calc_compensations: return the antialiasing compensation (rasterize_mode "antialiased").

    Returns:
        :class:`Projection`.
    """
    means_c, halves_c = world_to_cam(means, quat_scale_to_covar_half(quats, scales), viewmats)
    depths_raw = means_c[..., 2]
    # z > 0 additionally guards the division when a caller passes near_plane <= 0.
    valid = (depths_raw >= near_plane) & (depths_raw <= far_plane) & (depths_raw > 0)
    # Replace invalid depths before dividing: torch.where would otherwise route inf/NaN gradients of the unused branch.
    safe_means_c = torch.where(valid[..., None], means_c, torch.ones_like(means_c))
    means2d, covars2d = persp_proj(safe_means_c, halves_c, Ks, width, height)

    a, b, c = covars2d.unbind(-1)
    det_orig = a * c - b * b
    a = a + eps2d
    c = c + eps2d
    det = a * c - b * b
    valid = valid & (det > 0)
    safe_det = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / safe_det, -b / safe_det, a / safe_det], dim=-1)

    compensations = None
    if calc_compensations:
        ratio = det_orig / safe_det
        positive = valid & (ratio > 0)
        compensations = torch.where(positive, torch.sqrt(torch.where(positive, ratio, torch.ones_like(ratio))), 0.0 * ratio)

    with torch.no_grad():
        extent = torch.full_like(det, EXTENT_SIGMA)
        if opacities is not None:
            opacity = opacities.detach()[None, :].expand_as(det)
            if compensations is not None:
                opacity = opacity * compensations.detach()
            valid = valid & (opacity >= ALPHA_THRESHOLD)
            log_ratio = torch.log(torch.clamp(opacity, min=ALPHA_THRESHOLD) / ALPHA_THRESHOLD)
            extent = torch.minimum(extent, torch.sqrt(2.0 * log_ratio))
        var_x = torch.where(valid, a.detach(), torch.zeros_like(det))
        var_y = torch.where(valid, c.detach(), torch.zeros_like(det))
        radius_x = torch.ceil(extent * torch.sqrt(var_x.clamp(min=0)))
        radius_y = torch.ceil(extent * torch.sqrt(var_y.clamp(min=0)))
        valid = valid & ~((radius_x <= radius_clip) & (radius_y <= radius_clip))
        mx, my = means2d.detach()[..., 0], means2d.detach()[..., 1]
        outside = (mx + radius_x <= 0) | (mx - radius_x >= width) | (my + radius_y <= 0) | (my - radius_y >= height)
        valid = valid & ~outside
        # Saturate far below int32's limit: a Gaussian of scale 1e4 right in front of the camera can exceed 2^31 px.
        radius_max = float(RADIUS_MAX)
        radii = torch.stack([radius_x, radius_y], dim=-1).clamp(max=radius_max)
        radii = torch.where(valid[..., None], radii, torch.zeros_like(radii)).to(torch.int32)

    zero = torch.zeros((), dtype=means.dtype, device=means.device)
    means2d = torch.where(valid[..., None], means2d, zero)
    depths = torch.where(valid, depths_raw, zero)
    conics = torch.where(valid[..., None], conics, zero)
    if compensations is not None:
        compensations = torch.where(valid, compensations, zero)
    return Projection(radii, means2d, depths, conics, compensations)

