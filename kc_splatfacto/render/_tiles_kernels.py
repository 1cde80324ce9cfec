"""numba counting-sort tile binning for CPU tensors (used by ``tiles.isect_tiles``; same output as the sort)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def bin_pairs_by_tile(order, n_gauss, tile_min_x, tile_min_y, tile_max_x, tile_max_y, depth_bits, n_tiles,
                      tile_width, tile_bits, depth_shift, isect_ids, flatten_ids):
    """Write the intersections of the pairs in ``order`` bucketed by (camera, tile), keeping ``order`` inside a bucket.

    ``order`` lists the visible flattened pair indices sorted by (camera, depth, index), so the buckets come out
    sorted by (camera, tile, depth, index): the order a stable sort of gsplat's keys gives, in O(M) after that
    O(N log N) sort. ``depth_shift`` is ``constants.DEPTH_BITS`` (an argument: numba's disk cache freezes globals).
    Fills ``isect_ids`` and ``flatten_ids`` ([M]) and returns the bucket starts ([C * n_tiles]).
    """
    n_buckets = (tile_min_x.size // n_gauss) * n_tiles
    starts = np.zeros(n_buckets + 1, np.int64)
    for k in range(order.size):
        p = order[k]
        base = (p // n_gauss) * n_tiles + 1
        for ty in range(tile_min_y[p], tile_max_y[p]):
            for tx in range(tile_min_x[p], tile_max_x[p]):
                starts[base + ty * tile_width + tx] += 1
    for b in range(n_buckets):
        starts[b + 1] += starts[b]
    cursor = starts[:n_buckets].copy()
    for k in range(order.size):
        p = order[k]
        cam = p // n_gauss
        for ty in range(tile_min_y[p], tile_max_y[p]):
            for tx in range(tile_min_x[p], tile_max_x[p]):
                tile = ty * tile_width + tx
                b = cam * n_tiles + tile
                pos = cursor[b]
                cursor[b] = pos + 1
                isect_ids[pos] = (cam << (depth_shift + tile_bits)) | (tile << depth_shift) | depth_bits[p]
                flatten_ids[pos] = p
    return starts[:n_buckets]
