"""Gaussian parameters and their initialization (Splatfacto's ``populate_modules``).

Parameter layout (the shared contract, ``model.gauss_params``):
    means [N, 3], scales [N, 3] (log), quats [N, 4] (wxyz, unnormalized), opacities [N, 1] (logit),
    features_dc [N, 3] (SH degree-0 coefficient), features_rest [N, (D+1)^2 - 1, 3].
"""

from __future__ import annotations

import math

import numpy as np
import torch

from kc_splatfacto.render.constants import SH_C0

INITIAL_OPACITY = 0.1
"""Splatfacto's initial opacity of every Gaussian"""
KNN_NEIGHBOURS = 3
"""initial scale = mean distance to this many nearest neighbours"""
MIN_INITIAL_SCALE = 1e-7
"""floor of the initial scale (relative to the scene scale): duplicated seed points are at distance 0"""
LONE_POINT_SCALE = 0.01
"""initial scale (relative to the scene scale) of a Gaussian with no neighbour at all (a single seed point)"""


def num_sh_bases(degree: int) -> int:
    """(degree + 1)^2 coefficients per colour channel."""
    return (degree + 1) ** 2


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """Degree-0 SH coefficient whose colour (``sh * C0 + 0.5``) is ``rgb`` (any shape, values in [0, 1])."""
    return (rgb - 0.5) / SH_C0


def random_quat_tensor(n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """[n, 4] uniformly distributed unit quaternions (Shoemake's method, as Splatfacto)."""
    u, v, w = torch.rand(3, n, generator=generator)
    return torch.stack(
        [
            torch.sqrt(1 - u) * torch.sin(2 * math.pi * v),
            torch.sqrt(1 - u) * torch.cos(2 * math.pi * v),
            torch.sqrt(u) * torch.sin(2 * math.pi * w),
            torch.sqrt(u) * torch.cos(2 * math.pi * w),
        ],
        dim=-1,
    )


def knn_mean_distance(points: torch.Tensor, k: int = KNN_NEIGHBOURS) -> torch.Tensor:
    """Mean Euclidean distance of each point to its ``k`` nearest other points.

    Args:
        points: [N, 3].
    Returns:
        [N] float32; with fewer than ``k`` other points, the mean over those there are; NaN where there are none.
    """
    from scipy.spatial import cKDTree

    xyz = points.detach().cpu().double().numpy()
    n = xyz.shape[0]
    if n <= 1:
        return torch.full((n,), float("nan"))
    k_eff = min(k, n - 1)
    distances, _ = cKDTree(xyz).query(xyz, k=k_eff + 1)  # column 0 is the point itself
    return torch.from_numpy(np.asarray(distances, dtype=np.float64)[:, 1:].mean(axis=1)).float()


def init_gaussian_params(
    points: torch.Tensor | None,
    colors: torch.Tensor | None,
    *,
    sh_degree: int = 3,
    scene_scale: float = 1.0,
    num_random: int = 50000,
    random_scale: float = 10.0,
    generator: torch.Generator | None = None,
) -> torch.nn.ParameterDict:
    """Splatfacto's initial Gaussians: one per seed point, or ``num_random`` uniform in a cube.

    Args:
        points: [N, 3] seed points, or None for random initialization in the cube of side
            ``random_scale * scene_scale`` centred at the origin.
        colors: [N, 3] uint8 (or float in [0, 1]) seed colours, or None (random colours).
        sh_degree: highest SH degree; 0 stores colours as logits (Splatfacto's "colour only" mode).
    Returns:
        ParameterDict with the contract's names; scales are log(mean distance to the 3 nearest neighbours).
    """
    if points is None:
        means = (torch.rand(num_random, 3, generator=generator) - 0.5) * (random_scale * scene_scale)
        colors = None
    else:
        means = torch.as_tensor(points, dtype=torch.float32).reshape(-1, 3).clone()
        if means.shape[0] == 0:
            raise ValueError("no seed points: the dataparser gave 0 points; use random initialization (random_init=True)")
        if not torch.isfinite(means).all():
            raise ValueError(f"{int((~torch.isfinite(means)).any(-1).sum())} seed points are not finite")
    n = means.shape[0]
    distances = knn_mean_distance(means)
    distances = torch.where(torch.isnan(distances), torch.full_like(distances, LONE_POINT_SCALE * scene_scale), distances)
    distances = distances.clamp_min(MIN_INITIAL_SCALE * scene_scale)
    scales = torch.log(distances)[:, None].repeat(1, 3)
    quats = random_quat_tensor(n, generator)
    dim_sh = num_sh_bases(sh_degree)
    if colors is not None and len(colors) > 0:
        rgb = torch.as_tensor(colors).reshape(-1, 3)
        if len(rgb) != n:
            raise ValueError(f"{len(rgb)} seed colours for {n} seed points")
        rgb = rgb.float() / 255.0 if rgb.dtype == torch.uint8 else rgb.float()
        if sh_degree > 0:
            features_dc = rgb_to_sh(rgb)
        else:
            features_dc = torch.logit(rgb, eps=1e-10)
    else:
        features_dc = torch.rand(n, 3, generator=generator)
    features_rest = torch.zeros(n, dim_sh - 1, 3)
    opacities = torch.logit(torch.full((n, 1), INITIAL_OPACITY))
    return torch.nn.ParameterDict(
        {
            "means": torch.nn.Parameter(means),
            "scales": torch.nn.Parameter(scales),
            "quats": torch.nn.Parameter(quats),
            "features_dc": torch.nn.Parameter(features_dc),
            "features_rest": torch.nn.Parameter(features_rest),
            "opacities": torch.nn.Parameter(opacities),
        }
    )
