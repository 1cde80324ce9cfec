"""numba tile binning for CPU tensors (``tiles.isect_tiles`` / ``bin_tiles_cpu``): the output of gsplat's
``isect_tiles`` + stable key sort + ``isect_offset_encode``, in O(M) with no comparison sort.

1. Per pair, in parallel: the tile box, as ``tiles.tile_bounds`` computes it in float32 (min inclusive, max
   exclusive, clamped).
2. The visible pairs sorted by (camera, float32 depth bits) with a stable LSD radix sort on 16-bit digits, so equal
   keys keep the pair order; their boxes gathered into that order once, in parallel (the passes below would
   otherwise read them in depth order, a cache miss per pair).
3. Counting sort into (camera, tile) buckets, in that order: the buckets come out sorted by (camera, tile, depth,
   pair index), the order a stable sort of gsplat's int64 keys gives; the bucket starts are ``isect_offsets``.

(Bucketing first and sorting each bucket by depth gives the same order but was slower: numba's per-bucket argsort
costs more than the gather it saves.)

``depth_shift`` is ``constants.DEPTH_BITS`` (an argument: numba's disk cache freezes globals).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

RADIX_BITS = 16


@njit(cache=True)
def _radix_sort_pairs(keys, pairs):
    """Stable sort of ``pairs`` by the non-negative int64 ``keys`` (LSD radix, RADIX_BITS per pass).
    -> (sorted keys, pairs in that order)."""
    n = keys.size
    max_key = 0
    for i in range(n):
        if keys[i] > max_key:
            max_key = keys[i]
    n_buckets = 1 << RADIX_BITS
    mask = n_buckets - 1
    keys_tmp = np.empty_like(keys)
    pairs_tmp = np.empty_like(pairs)
    counts = np.empty(n_buckets + 1, np.int64)
    shift = 0
    while shift == 0 or (max_key >> shift) > 0:
        counts[:] = 0
        for i in range(n):
            counts[((keys[i] >> shift) & mask) + 1] += 1
        for b in range(n_buckets):
            counts[b + 1] += counts[b]
        for i in range(n):
            d = (keys[i] >> shift) & mask
            pos = counts[d]
            counts[d] = pos + 1
            keys_tmp[pos] = keys[i]
            pairs_tmp[pos] = pairs[i]
        keys, keys_tmp = keys_tmp, keys
        pairs, pairs_tmp = pairs_tmp, pairs
        shift += RADIX_BITS
    return keys, pairs


@njit(parallel=True, cache=True)
def _tile_boxes(means2d, radii, tile_size, tile_width, tile_height, box, tiles_per_gauss, visible):
    """Fills box [C*N, 4] int32 (tile x0, y0, x1, y1), tiles_per_gauss [C,N] and visible [C*N] for every pair, in
    parallel (each pair writes only its own entries)."""
    n_cams = radii.shape[0]
    n_gauss = radii.shape[1]
    ts = np.float32(tile_size)
    lim_x = np.float32(tile_width)
    lim_y = np.float32(tile_height)
    for p in prange(n_cams * n_gauss):
        c = p // n_gauss
        g = p - c * n_gauss
        rx = radii[c, g, 0]
        ry = radii[c, g, 1]
        if rx <= 0 or ry <= 0:
            box[p, 0] = box[p, 1] = box[p, 2] = box[p, 3] = 0
            continue
        # float32 as tiles.tile_bounds: centre / tile_size -/+ radius / tile_size, floor/ceil, clamp
        cx = np.float32(means2d[c, g, 0]) / ts
        cy = np.float32(means2d[c, g, 1]) / ts
        ex = np.float32(rx) / ts
        ey = np.float32(ry) / ts
        x0 = min(max(np.float32(math.floor(cx - ex)), np.float32(0.0)), lim_x)
        y0 = min(max(np.float32(math.floor(cy - ey)), np.float32(0.0)), lim_y)
        x1 = min(max(np.float32(math.ceil(cx + ex)), np.float32(0.0)), lim_x)
        y1 = min(max(np.float32(math.ceil(cy + ey)), np.float32(0.0)), lim_y)
        box[p, 0] = np.int32(x0)
        box[p, 1] = np.int32(y0)
        box[p, 2] = np.int32(x1)
        box[p, 3] = np.int32(y1)
        tiles_per_gauss[c, g] = np.int32(max(box[p, 2] - box[p, 0], 0) * max(box[p, 3] - box[p, 1], 0))
        visible[p] = True


@njit(cache=True)
def bin_tiles(means2d, radii, depths, tile_size, tile_width, tile_height, tile_bits, depth_shift):
    """Intersections of every visible (camera, Gaussian) pair with the tiles its radius box touches.

    means2d [C,N,2] float32, radii [C,N,2] int32 (a pair is visible when both are > 0), depths [C,N] float32 (> 0
    for visible pairs). Returns tiles_per_gauss [C,N] int32, isect_ids [M] int64 (``camera << (depth_shift +
    tile_bits) | tile << depth_shift | depth bits``), flatten_ids [M] int32 (index into C*N), isect_offsets
    [C * tile_height * tile_width] int32 (start of each (camera, tile) run; empty tiles point at the next run).
    """
    n_cams = depths.shape[0]
    n_gauss = depths.shape[1]
    n_tiles = tile_width * tile_height
    n_pairs = n_cams * n_gauss
    box = np.empty((n_pairs, 4), np.int32)  # tile x0, y0, x1, y1
    tiles_per_gauss = np.zeros((n_cams, n_gauss), np.int32)
    depth_bits = depths.reshape(-1).view(np.uint32)
    visible = np.zeros(n_pairs, np.bool_)
    _tile_boxes(means2d, radii, tile_size, tile_width, tile_height, box, tiles_per_gauss, visible)
    n_visible = 0
    for p in range(n_pairs):
        n_visible += 1 if visible[p] else 0
    keys = np.empty(n_visible, np.int64)
    pairs = np.empty(n_visible, np.int64)
    k = 0
    for p in range(n_pairs):
        if visible[p]:
            keys[k] = ((p // n_gauss) << 32) | np.int64(depth_bits[p])
            pairs[k] = p
            k += 1
    sorted_keys, order = _radix_sort_pairs(keys, pairs)
    # the boxes in sorted order, gathered once in parallel: the passes below then read them sequentially
    sorted_box = np.empty((order.size, 4), np.int32)
    _gather_rows(box, order, sorted_box)
    n_buckets = n_cams * n_tiles
    starts = np.zeros(n_buckets + 1, np.int64)
    for k in range(order.size):
        base = (order[k] // n_gauss) * n_tiles + 1
        for ty in range(sorted_box[k, 1], sorted_box[k, 3]):
            for tx in range(sorted_box[k, 0], sorted_box[k, 2]):
                starts[base + ty * tile_width + tx] += 1
    for b in range(n_buckets):
        starts[b + 1] += starts[b]
    n_isects = starts[n_buckets]
    isect_ids = np.empty(n_isects, np.int64)
    flatten_ids = np.empty(n_isects, np.int32)
    cursor = starts[:n_buckets].copy()
    depth_mask = (np.int64(1) << 32) - 1
    for k in range(order.size):
        p = order[k]
        cam = p // n_gauss
        depth = sorted_keys[k] & depth_mask
        for ty in range(sorted_box[k, 1], sorted_box[k, 3]):
            for tx in range(sorted_box[k, 0], sorted_box[k, 2]):
                tile = ty * tile_width + tx
                b = cam * n_tiles + tile
                pos = cursor[b]
                cursor[b] = pos + 1
                isect_ids[pos] = (cam << (depth_shift + tile_bits)) | (tile << depth_shift) | depth
                flatten_ids[pos] = p
    offsets = starts[:n_buckets].astype(np.int32)
    return tiles_per_gauss, isect_ids, flatten_ids, offsets


@njit(parallel=True, cache=True)
def _gather_rows(src, rows, out):
    """out[k] = src[rows[k]] for 2D arrays, in parallel."""
    for k in prange(rows.shape[0]):
        for j in range(src.shape[1]):
            out[k, j] = src[rows[k], j]
