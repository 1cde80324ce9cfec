"""Render layer: gsplat-compatible ``rasterization()`` with reference (torch), cpu (compiled) and gsplat rasterizers."""

from .non_finite import NonFiniteInputError
from .projection import (
    Projection,
    fully_fused_projection,
    persp_proj,
    quat_scale_to_covar_half,
    quat_to_rotmat,
    world_to_cam,
)
from .rasterization import RASTERIZERS, RENDER_MODES, rasterization, resolve_rasterizer
from .rasterize_torch import rasterize_to_pixels_torch
from .sh import SplitSH, num_sh_bases, sh_bases, sh_to_rgb, spherical_harmonics
from .tiles import TileIntersections, isect_offset_encode, isect_tiles, tile_grid

__all__ = [
    "NonFiniteInputError",
    "RASTERIZERS",
    "RENDER_MODES",
    "Projection",
    "SplitSH",
    "TileIntersections",
    "fully_fused_projection",
    "isect_offset_encode",
    "isect_tiles",
    "num_sh_bases",
    "persp_proj",
    "quat_scale_to_covar_half",
    "quat_to_rotmat",
    "rasterization",
    "rasterize_to_pixels_torch",
    "resolve_rasterizer",
    "sh_bases",
    "sh_to_rgb",
    "spherical_harmonics",
    "tile_grid",
    "world_to_cam",
]
