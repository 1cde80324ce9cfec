"""Tile binning against a brute-force python loop over (camera, Gaussian, tile)."""

import math
import struct

import numpy as np
import pytest
import torch

from kc_splatfacto.render import tiles
from kc_splatfacto.render import tiles as tiles_module
from kc_splatfacto.render.tiles import isect_offset_encode, isect_tiles, tile_grid


@pytest.fixture(params=["compiled", "key_sort"])
def binning(request, monkeypatch):
    """Both binning routes: the compiled radix + counting sort (CPU default) and the vectorized key sort (other
    devices)."""
    if request.param == "key_sort":

        def key_sort(means2d, radii, depths, tile_size, tw, th):
            tmin, tmax = tiles.tile_bounds(means2d, radii, tile_size, tw, th)
            visible = (radii[..., 0] > 0) & (radii[..., 1] > 0)
            span = (tmax - tmin).clamp(min=0)
            counts = torch.where(visible, span[..., 0] * span[..., 1], torch.zeros_like(span[..., 0]))
            isect_ids, flatten_ids = tiles._bin_sort_keys(depths, tmin, span, counts, tw, th, True)
            offsets = isect_offset_encode(isect_ids, depths.shape[0], tw, th)
            return counts.to(torch.int32), isect_ids, flatten_ids.to(torch.int32), offsets

        monkeypatch.setattr(tiles, "bin_tiles_cpu", key_sort)
    return request.param


def bruteforce_isects(means2d, radii, depths, tile_size, tile_width, tile_height):
    """Every tile whose index range the per-axis radius box reaches, as gsplat's intersect_tile_kernel; sorted by
    (camera, tile, depth, flattened index)."""
    n_cameras, n = depths.shape
    rows = []
    for c in range(n_cameras):
        for g in range(n):
            rx, ry = int(radii[c, g, 0]), int(radii[c, g, 1])
            if rx <= 0 or ry <= 0:
                continue
            mx, my = float(means2d[c, g, 0]) / tile_size, float(means2d[c, g, 1]) / tile_size
            x0 = min(max(0, math.floor(mx - rx / tile_size)), tile_width)
            x1 = min(max(0, math.ceil(mx + rx / tile_size)), tile_width)
            y0 = min(max(0, math.floor(my - ry / tile_size)), tile_height)
            y1 = min(max(0, math.ceil(my + ry / tile_size)), tile_height)
            depth32 = struct.unpack("f", struct.pack("f", float(depths[c, g])))[0]
            for ty in range(y0, y1):
                for tx in range(x0, x1):
                    rows.append((c, ty * tile_width + tx, depth32, c * n + g))
    rows.sort()
    return rows


def random_bins(n_cameras, n, width, height, seed, tile_size=16):
    g = torch.Generator().manual_seed(seed)
    means2d = torch.rand(n_cameras, n, 2, generator=g) * torch.tensor([width * 1.4, height * 1.4]) - torch.tensor(
        [width * 0.2, height * 0.2]
    )
    radii = torch.randint(0, 40, (n_cameras, n, 2), generator=g, dtype=torch.int32)
    radii[torch.rand(n_cameras, n, generator=g) < 0.15] = 0  # culled pairs
    depths = torch.rand(n_cameras, n, generator=g) * 10 + 0.1
    depths[0, :5] = 3.0  # equal depths: the order must fall back to the Gaussian index
    return means2d, radii, depths


@pytest.mark.parametrize("width,height,tile_size", [(100, 75, 16), (64, 64, 16), (37, 50, 8), (1, 1, 16)])
def test_isect_tiles_equal_bruteforce(width, height, tile_size, binning):
    n_cameras, n = 3, 80
    means2d, radii, depths = random_bins(n_cameras, n, width, height, seed=width, tile_size=tile_size)
    tile_width, tile_height = tile_grid(width, height, tile_size)
    assert (tile_width, tile_height) == (math.ceil(width / tile_size), math.ceil(height / tile_size))
    tiles_per_gauss, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile_size, tile_width, tile_height)
    rows = bruteforce_isects(means2d, radii, depths, tile_size, tile_width, tile_height)
    assert len(rows) > 0
    n_bits = (tile_width * tile_height).bit_length()
    assert flatten_ids.tolist() == [r[3] for r in rows]
    cams = (isect_ids >> (32 + n_bits)).tolist()
    tiles = ((isect_ids >> 32) & ((1 << n_bits) - 1)).tolist()
    depth_bits = (isect_ids & 0xFFFFFFFF).to(torch.int64).numpy().astype(np.uint32).view(np.float32)
    assert cams == [r[0] for r in rows]
    assert tiles == [r[1] for r in rows]
    np.testing.assert_array_equal(depth_bits, np.array([r[2] for r in rows], dtype=np.float32))
    counts = np.zeros((n_cameras, n), dtype=np.int64)
    for r in rows:
        counts[r[3] // n, r[3] % n] += 1
    np.testing.assert_array_equal(tiles_per_gauss.numpy(), counts)

    offsets = isect_offset_encode(isect_ids, n_cameras, tile_width, tile_height)
    assert offsets.shape == (n_cameras, tile_height, tile_width) and offsets.dtype == torch.int32
    keys = [(r[0], r[1]) for r in rows]
    for c in range(n_cameras):
        for t in range(tile_width * tile_height):
            # first intersection at or after (c, t): where the run of this tile starts (or the next one does)
            first = next((k for k, key in enumerate(keys) if key >= (c, t)), len(keys))
            assert offsets[c, t // tile_width, t % tile_width] == first
    # the one-pass CPU binning returns the same offsets with the intersections
    fused = tiles_module.bin_tiles_cpu(means2d, radii, depths, tile_size, tile_width, tile_height)
    assert torch.equal(fused[1], isect_ids) and torch.equal(fused[2], flatten_ids) and torch.equal(fused[3], offsets)


def test_empty_intersections_give_zero_offsets(binning):
    means2d = torch.zeros(2, 3, 2)
    radii = torch.zeros(2, 3, 2, dtype=torch.int32)
    depths = torch.ones(2, 3)
    tiles_per_gauss, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, 16, 4, 3)
    assert isect_ids.numel() == 0 and flatten_ids.numel() == 0 and (tiles_per_gauss == 0).all()
    offsets = isect_offset_encode(isect_ids, 2, 4, 3)
    assert offsets.shape == (2, 3, 4) and (offsets == 0).all()


def test_too_many_cameras_for_the_key_is_a_clear_error():
    means2d, radii, depths = torch.zeros(2**12, 1, 2), torch.ones(2**12, 1, 2, dtype=torch.int32), torch.ones(2**12, 1)
    with pytest.raises(ValueError, match="do not fit"):
        isect_tiles(means2d, radii, depths, 16, 2**10, 2**10)
