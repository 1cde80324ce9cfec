"""Tile binning as gsplat 1.5.3's ``isect_tiles`` / ``isect_offset_encode`` (unpacked), vectorized in torch.

Each visible (camera, Gaussian) pair is listed once per tile its per-axis radius box touches. The int64 key
``camera << (32 + tile_n_bits) | tile << 32 | float32 bits of depth`` sorts intersections by camera, then tile, then
depth front to back (positive float32 bit patterns order like the floats; culling keeps depths >= near_plane > 0).
The sort is stable, so equal depths keep the Gaussian order, as gsplat's CUB radix sort does. CPU tensors take an
equivalent O(M) compiled route (:func:`bin_tiles_cpu`: radix-sort the pairs by depth once, then bucket by tile, and
the offsets come out of the bucketing); other devices sort the keys.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from kc_splatfacto import backend

from .constants import DEPTH_BITS, ISECT_KEY_HIGH_BITS


def tile_grid(width: int, height: int, tile_size: int) -> tuple[int, int]:
    """(tile_width, tile_height): the number of tiles across and down, ``ceil(size / tile_size)``."""
    return (width + tile_size - 1) // tile_size, (height + tile_size - 1) // tile_size


def tile_n_bits(tile_width: int, tile_height: int) -> int:
    """Bits of the tile id in an isect key: ``floor(log2(n_tiles)) + 1`` as gsplat computes it."""
    return (tile_width * tile_height).bit_length()


def depth_key(depths: Tensor) -> Tensor:
    """float32 bit pattern of depths, zero-extended to int64 (gsplat's ``depth_id_enc``). [...] -> [...] int64."""
    bits = depths.detach().to(torch.float32).contiguous().view(torch.int32).to(torch.int64)
    return bits & 0xFFFFFFFF


def tile_bounds(means2d: Tensor, radii: Tensor, tile_size: int, tile_width: int, tile_height: int) -> tuple[Tensor, Tensor]:
    """Tile box of each pair: min inclusive, max exclusive, clamped to the grid.

    Args:
        means2d: [C, N, 2]; radii: [C, N, 2] int32.

    Returns:
        tile_min, tile_max: [C, N, 2] int64 (x, y).
    """
    centre = means2d.detach().to(torch.float32) / float(tile_size)
    extent = radii.to(torch.float32) / float(tile_size)
    limit = torch.tensor([tile_width, tile_height], dtype=torch.float32, device=means2d.device)
    # CUDA's float -> uint32 conversion saturates negatives at 0; clamping reproduces it.
    tile_min = torch.minimum(torch.clamp(torch.floor(centre - extent), min=0.0), limit).to(torch.int64)
    tile_max = torch.minimum(torch.clamp(torch.ceil(centre + extent), min=0.0), limit).to(torch.int64)
    return tile_min, tile_max


class TileIntersections(NamedTuple):
    tiles_per_gauss: Tensor  # [C, N] int32
    isect_ids: Tensor  # [M] int64, sorted
    flatten_ids: Tensor  # [M] int32, index into the flattened [C * N]


@torch.no_grad()
def isect_tiles(
    means2d: Tensor,
    radii: Tensor,
    depths: Tensor,
    tile_size: int,
    tile_width: int,
    tile_height: int,
    sort: bool = True,
) -> TileIntersections:
    """List every (camera, Gaussian, tile) intersection, sorted by camera, tile and depth.

    Args:
        means2d: [C, N, 2] projected means; radii: [C, N, 2] int32 (0 = culled); depths: [C, N].
        tile_size: pixels per tile side; tile_width, tile_height: the tile grid.
        sort: sort the keys (gsplat's default).

    Returns:
        :class:`TileIntersections`.
    """
    n_cameras, n_gauss = depths.shape
    n_bits = tile_n_bits(tile_width, tile_height)
    camera_bits = max(n_cameras, 1).bit_length()
    if n_bits + camera_bits > ISECT_KEY_HIGH_BITS:
        raise ValueError(
            f"{n_cameras} cameras x {tile_width * tile_height} tiles do not fit the 32-bit camera|tile key; "
            "render fewer cameras per call or use a larger tile_size"
        )
    tile_min, tile_max = tile_bounds(means2d, radii, tile_size, tile_width, tile_height)
    visible = (radii[..., 0] > 0) & (radii[..., 1] > 0)
    span = (tile_max - tile_min).clamp(min=0)  # [C, N, 2]
    counts = torch.where(visible, span[..., 0] * span[..., 1], torch.zeros_like(span[..., 0]))  # [C, N]
    if sort and backend.compiled(means2d) and n_gauss > 0:
        tiles_per_gauss, isect_ids, flatten_ids, _ = bin_tiles_cpu(means2d, radii, depths, tile_size, tile_width,
                                                                   tile_height)
        return TileIntersections(tiles_per_gauss, isect_ids, flatten_ids)
    else:
        isect_ids, flatten_ids = _bin_sort_keys(depths, tile_min, span, counts, tile_width, tile_height, sort)
    return TileIntersections(counts.to(torch.int32), isect_ids, flatten_ids.to(torch.int32))


def _bin_sort_keys(
    depths: Tensor, tile_min: Tensor, span: Tensor, counts: Tensor, tile_width: int, tile_height: int, sort: bool
) -> tuple[Tensor, Tensor]:
    """Vectorized binning: every intersection's key in pair order, then a stable sort (any device). -> [M], [M]."""
    n_cameras, n_gauss = depths.shape
    device = depths.device
    n_bits = tile_n_bits(tile_width, tile_height)
    counts_flat = counts.reshape(-1)
    n_isects = int(counts_flat.sum().item())
    flatten_ids = torch.repeat_interleave(torch.arange(n_cameras * n_gauss, device=device), counts_flat)
    # Position of each intersection inside its pair's box, row-major over (y, x).
    starts = torch.cumsum(counts_flat, dim=0) - counts_flat
    local = torch.arange(n_isects, device=device) - starts[flatten_ids]
    span_x = span[..., 0].reshape(-1)[flatten_ids].clamp(min=1)
    tile_x = tile_min[..., 0].reshape(-1)[flatten_ids] + local % span_x
    tile_y = tile_min[..., 1].reshape(-1)[flatten_ids] + local // span_x
    tile_ids = tile_y * tile_width + tile_x
    camera_ids = flatten_ids // max(n_gauss, 1)
    isect_ids = (
        (camera_ids << (DEPTH_BITS + n_bits)) | (tile_ids << DEPTH_BITS) | depth_key(depths).reshape(-1)[flatten_ids]
    )
    if sort and n_isects > 0:
        isect_ids, order = torch.sort(isect_ids, stable=True)
        flatten_ids = flatten_ids[order]
    return isect_ids, flatten_ids


@torch.no_grad()
def bin_tiles_cpu(
    means2d: Tensor, radii: Tensor, depths: Tensor, tile_size: int, tile_width: int, tile_height: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`isect_tiles` (sorted) and :func:`isect_offset_encode` in one compiled O(M) pass, for CPU tensors.

    Args:
        means2d: [C, N, 2]; radii: [C, N, 2] int32 (0 = culled); depths: [C, N].

    Returns:
        tiles_per_gauss [C, N] int32, isect_ids [M] int64, flatten_ids [M] int32, isect_offsets [C, tile_height,
        tile_width] int32: the same tensors as the two functions.
    """
    from ._tiles_kernels import bin_tiles

    n_cameras = depths.shape[0]
    n_bits = tile_n_bits(tile_width, tile_height)
    if n_bits + max(n_cameras, 1).bit_length() > ISECT_KEY_HIGH_BITS:
        raise ValueError(
            f"{n_cameras} cameras x {tile_width * tile_height} tiles do not fit the 32-bit camera|tile key; "
            "render fewer cameras per call or use a larger tile_size"
        )

    def f32(t: Tensor):
        return t.detach().to(torch.float32).contiguous().numpy()

    tiles_per_gauss, isect_ids, flatten_ids, offsets = bin_tiles(
        f32(means2d), radii.to(torch.int32).contiguous().numpy(), f32(depths), int(tile_size), int(tile_width),
        int(tile_height), n_bits, DEPTH_BITS,
    )
    return (torch.from_numpy(tiles_per_gauss), torch.from_numpy(isect_ids), torch.from_numpy(flatten_ids),
            torch.from_numpy(offsets).reshape(n_cameras, tile_height, tile_width))


@torch.no_grad()
def isect_offset_encode(isect_ids: Tensor, n_cameras: int, tile_width: int, tile_height: int) -> Tensor:
    """Start of each (camera, tile) run in the sorted intersections; empty tiles point at the next run.

    Args:
        isect_ids: [M] sorted keys from :func:`isect_tiles`.
        n_cameras: C; tile_width, tile_height: the tile grid.

    Returns:
        [C, tile_height, tile_width] int32 offsets; the run of tile t ends where the next offset starts (or at M).
    """
    n_tiles = tile_width * tile_height
    n_bits = tile_n_bits(tile_width, tile_height)
    key = isect_ids >> DEPTH_BITS
    camera_ids = key >> n_bits
    tile_ids = key & ((1 << n_bits) - 1)
    counts = torch.bincount(camera_ids * n_tiles + tile_ids, minlength=n_cameras * n_tiles)
    offsets = torch.cumsum(counts, dim=0) - counts
    return offsets.reshape(n_cameras, tile_height, tile_width).to(torch.int32)
