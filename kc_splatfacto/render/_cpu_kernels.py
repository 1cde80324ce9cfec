"""numba kernels of the fast CPU rasterizer (gsplat 1.5.3 ``RasterizeToPixels3DGS{Fwd,Bwd}.cu`` semantics).

Layout shared by the kernels (all arrays C-contiguous numpy):

- ``packed [M, PACK_HEAD + D] float32``: one row per intersection ``m`` (tile-sorted order), the Gaussian
  ``flatten_ids[m]`` gathered once so that a tile streams through contiguous memory:
  ``x, y, conic_a, conic_b, conic_c, opacity, extent_x, extent_y, color[0..D)``. ``extent_*`` is a conservative
  half-size (px) of the ellipse where ``alpha >= alpha_threshold``: a tile only visits pixels inside it.
- ``tile_offsets [C * tile_h * tile_w] int32``: first intersection of each tile (gsplat's ``isect_offsets``
  flattened); the last tile ends at ``M``.
- Per-pixel forward state ``T_final [C, H, W] float32`` (transmittance after the last contributor) and
  ``last_ids [C, H, W] int32`` (intersection index of the last contributor, -1 when none).
- ``isect_grads [M, GRAD_HEAD + D] float32``: per-intersection gradients written by the tile that owns the
  intersection (each intersection belongs to exactly one tile, so no write races), reduced to Gaussians by
  ``reduce_isect_grads`` in a fixed serial order (deterministic).

The gsplat constants (alpha clamp, alpha threshold, transmittance threshold) are kernel ARGUMENTS, not globals:
numba freezes globals into its on-disk cache, and a cache keyed on this file alone would not see a change in
``constants.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# packed row: x, y, conic a, b, c, opacity, extent x, extent y, then D colour channels
PACK_HEAD = 8
# gradient row: v_x, v_y, v_conic a, b, c, v_opacity, |v_x|, |v_y| summed per pixel (absgrad), then D v_colors
GRAD_HEAD = 8

_F32 = np.float32


@njit(parallel=True, cache=True, fastmath=False)
def pack_isects(means2d, conics, opacities, colors, flatten_ids, alpha_threshold, packed):
    """Gather per-intersection Gaussian data and the conservative ellipse extent (fills ``packed``).

    means2d [G,2], conics [G,3], opacities [G], colors [G,D] float32 (G = C*N); flatten_ids [M] int32.
    The extent solves ``0.5 d^T Q d <= log(opacity / alpha_threshold)`` (beyond it ``alpha < threshold``
    and gsplat skips the pixel); a conic that is not positive definite gets an unbounded extent (every
    pixel of the tile is visited and tested exactly as gsplat does).
    """
    n_isects = flatten_ids.shape[0]
    n_channels = colors.shape[1]
    for m in prange(n_isects):
        g = flatten_ids[m]
        a = conics[g, 0]
        b = conics[g, 1]
        c = conics[g, 2]
        o = opacities[g]
        packed[m, 0] = means2d[g, 0]
        packed[m, 1] = means2d[g, 1]
        packed[m, 2] = a
        packed[m, 3] = b
        packed[m, 4] = c
        packed[m, 5] = o
        # float64 on purpose: the extent must never be smaller than the float32 test it stands in for
        a64 = np.float64(a)
        b64 = np.float64(b)
        c64 = np.float64(c)
        det = a64 * c64 - b64 * b64
        if not (o >= alpha_threshold):
            # opacity * exp(-sigma) <= opacity < threshold for every sigma >= 0: no pixel passes
            ex = -1.0
            ey = -1.0
        elif a64 > 0.0 and c64 > 0.0 and det > 0.0 and math.isfinite(det):
            sigma_max = math.log(np.float64(o) / np.float64(alpha_threshold)) + 1e-3
            ex = math.sqrt(2.0 * sigma_max * c64 / det) * 1.001 + 1e-2
            ey = math.sqrt(2.0 * sigma_max * a64 / det) * 1.001 + 1e-2
        else:
            ex = np.inf
            ey = np.inf
        packed[m, 6] = ex
        packed[m, 7] = ey
        for k in range(n_channels):
            packed[m, PACK_HEAD + k] = colors[g, k]


@njit(inline="always")
def _pixel_range(center, extent, pixel_offset, lo, hi):
    """Pixels ``p`` in ``[lo, hi)`` whose centre ``p + pixel_offset`` is within ``extent`` of ``center``: (first, end)."""
    if not (extent >= 0.0):
        return lo, lo
    if extent == np.inf or not math.isfinite(center):
        return lo, hi
    first = math.ceil(np.float64(center) - np.float64(extent) - np.float64(pixel_offset))
    last = math.floor(np.float64(center) + np.float64(extent) - np.float64(pixel_offset))
    if first < lo:
        first = lo
    if last > hi - 1:
        last = hi - 1
    if last < first:
        return lo, lo
    return int(first), int(last) + 1


@njit(parallel=True, cache=True, fastmath=False)
def rasterize_fwd(
    packed,
    tile_offsets,
    backgrounds,
    n_cameras,
    image_height,
    image_width,
    tile_size,
    tile_height,
    tile_width,
    pixel_offset,
    max_alpha,
    alpha_threshold,
    transmittance_threshold,
    render_colors,
    T_final,
    last_ids,
):
    """Front-to-back compositing, one tile per task (fills render_colors [C,H,W,D], T_final, last_ids).

    backgrounds [C,D] float32 (zeros when the caller has none: ``T * 0`` adds nothing).
    """
    n_isects = packed.shape[0]
    n_channels = packed.shape[1] - PACK_HEAD
    tiles_per_image = tile_height * tile_width
    n_tiles = n_cameras * tiles_per_image
    half = _F32(0.5)
    one = _F32(1.0)
    for tile in prange(n_tiles):
        cam = tile // tiles_per_image
        tile_in_image = tile - cam * tiles_per_image
        tile_y = tile_in_image // tile_width
        tile_x = tile_in_image - tile_y * tile_width
        x0 = tile_x * tile_size
        y0 = tile_y * tile_size
        x1 = min(x0 + tile_size, image_width)
        y1 = min(y0 + tile_size, image_height)
        span_x = x1 - x0
        n_pix = span_x * (y1 - y0)
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1] if tile + 1 < n_tiles else n_isects

        T = np.ones(n_pix, dtype=np.float32)
        acc = np.zeros((n_pix, n_channels), dtype=np.float64)
        last = np.full(n_pix, -1, dtype=np.int32)
        done = np.zeros(n_pix, dtype=np.bool_)
        n_done = 0
        for m in range(start, end):
            if n_done == n_pix:
                break
            gx = packed[m, 0]
            gy = packed[m, 1]
            ca = packed[m, 2]
            cb = packed[m, 3]
            cc = packed[m, 4]
            op = packed[m, 5]
            j_first, j_end = _pixel_range(gx, packed[m, 6], pixel_offset, x0, x1)
            i_first, i_end = _pixel_range(gy, packed[m, 7], pixel_offset, y0, y1)
            for i in range(i_first, i_end):
                dy = gy - (_F32(i) + pixel_offset)
                row = (i - y0) * span_x - x0
                for j in range(j_first, j_end):
                    p = row + j
                    if done[p]:
                        continue
                    dx = gx - (_F32(j) + pixel_offset)
                    sigma = half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    alpha = min(max_alpha, op * math.exp(-sigma))
                    if sigma < 0 or alpha < alpha_threshold:
                        continue
                    next_T = T[p] * (one - alpha)
                    if next_T <= transmittance_threshold:
                        # gsplat: this pixel is done, exclusive (the Gaussian is not composited)
                        done[p] = True
                        n_done += 1
                        continue
                    vis = alpha * T[p]
                    for k in range(n_channels):
                        acc[p, k] += packed[m, PACK_HEAD + k] * vis
                    last[p] = m
                    T[p] = next_T
        for i in range(y0, y1):
            for j in range(x0, x1):
                p = (i - y0) * span_x + (j - x0)
                t = T[p]
                T_final[cam, i, j] = t
                last_ids[cam, i, j] = last[p]
                for k in range(n_channels):
                    render_colors[cam, i, j, k] = acc[p, k] + t * backgrounds[cam, k]


@njit(parallel=True, cache=True, fastmath=False)
def rasterize_bwd(
    packed,
    tile_offsets,
    backgrounds,
    T_final,
    last_ids,
    v_render_colors,
    v_render_alphas,
    n_cameras,
    image_height,
    image_width,
    tile_size,
    tile_height,
    tile_width,
    pixel_offset,
    max_alpha,
    alpha_threshold,
    isect_grads,
):
    """Back-to-front gradients per tile from each pixel's last contributor (fills isect_grads [M, 8+D]).

    Transmittance is recovered by division (``T /= 1 - alpha``) as gsplat does, in float64;
    ``buffer`` is the colour composited behind the current Gaussian. v_render_colors [C,H,W,D],
    v_render_alphas [C,H,W] float32; backgrounds [C,D] float32 (zeros when none).
    """
    n_isects = packed.shape[0]
    n_channels = packed.shape[1] - PACK_HEAD
    tiles_per_image = tile_height * tile_width
    n_tiles = n_cameras * tiles_per_image
    half = _F32(0.5)
    one = _F32(1.0)
    for tile in prange(n_tiles):
        cam = tile // tiles_per_image
        tile_in_image = tile - cam * tiles_per_image
        tile_y = tile_in_image // tile_width
        tile_x = tile_in_image - tile_y * tile_width
        x0 = tile_x * tile_size
        y0 = tile_y * tile_size
        x1 = min(x0 + tile_size, image_width)
        y1 = min(y0 + tile_size, image_height)
        span_x = x1 - x0
        n_pix = span_x * (y1 - y0)
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1] if tile + 1 < n_tiles else n_isects
        if end <= start:
            continue

        T = np.empty(n_pix, dtype=np.float64)
        T_fin = np.empty(n_pix, dtype=np.float64)
        last = np.empty(n_pix, dtype=np.int32)
        v_c = np.empty((n_pix, n_channels), dtype=np.float64)
        # d(out)/d(alpha) terms that do not depend on the Gaussian: T_final * (v_alpha_out - <bg, v_color>)
        alpha_term = np.empty(n_pix, dtype=np.float64)
        buffer = np.zeros((n_pix, n_channels), dtype=np.float64)
        tile_last = -1
        for i in range(y0, y1):
            for j in range(x0, x1):
                p = (i - y0) * span_x + (j - x0)
                t = np.float64(T_final[cam, i, j])
                T[p] = t
                T_fin[p] = t
                lp = last_ids[cam, i, j]
                last[p] = lp
                if lp > tile_last:
                    tile_last = lp
                bg_dot = 0.0
                for k in range(n_channels):
                    v = np.float64(v_render_colors[cam, i, j, k])
                    v_c[p, k] = v
                    bg_dot += np.float64(backgrounds[cam, k]) * v
                alpha_term[p] = t * (np.float64(v_render_alphas[cam, i, j]) - bg_dot)

        v_rgb = np.zeros(n_channels, dtype=np.float64)
        for m in range(min(tile_last, end - 1), start - 1, -1):
            gx = packed[m, 0]
            gy = packed[m, 1]
            ca = packed[m, 2]
            cb = packed[m, 3]
            cc = packed[m, 4]
            op = packed[m, 5]
            j_first, j_end = _pixel_range(gx, packed[m, 6], pixel_offset, x0, x1)
            i_first, i_end = _pixel_range(gy, packed[m, 7], pixel_offset, y0, y1)
            for k in range(n_channels):
                v_rgb[k] = 0.0
            v_ca = 0.0
            v_cb = 0.0
            v_cc = 0.0
            v_x = 0.0
            v_y = 0.0
            v_x_abs = 0.0
            v_y_abs = 0.0
            v_op = 0.0
            for i in range(i_first, i_end):
                dy = gy - (_F32(i) + pixel_offset)
                row = (i - y0) * span_x - x0
                for j in range(j_first, j_end):
                    p = row + j
                    if m > last[p]:
                        continue
                    dx = gx - (_F32(j) + pixel_offset)
                    sigma = half * (ca * dx * dx + cc * dy * dy) + cb * dx * dy
                    vis = math.exp(-sigma)
                    alpha = min(max_alpha, op * vis)
                    if sigma < 0 or alpha < alpha_threshold:
                        continue
                    ra = 1.0 / (1.0 - np.float64(alpha))
                    t = T[p] * ra
                    T[p] = t
                    fac = np.float64(alpha) * t
                    v_alpha = alpha_term[p] * ra
                    for k in range(n_channels):
                        vk = v_c[p, k]
                        ck = np.float64(packed[m, PACK_HEAD + k])
                        v_rgb[k] += fac * vk
                        v_alpha += (ck * t - buffer[p, k] * ra) * vk
                        buffer[p, k] += ck * fac
                    if op * vis <= max_alpha:
                        v_sigma = -np.float64(op * vis) * v_alpha
                        dx64 = np.float64(dx)
                        dy64 = np.float64(dy)
                        v_ca += 0.5 * v_sigma * dx64 * dx64
                        v_cb += v_sigma * dx64 * dy64
                        v_cc += 0.5 * v_sigma * dy64 * dy64
                        gxp = v_sigma * (np.float64(ca) * dx64 + np.float64(cb) * dy64)
                        gyp = v_sigma * (np.float64(cb) * dx64 + np.float64(cc) * dy64)
                        v_x += gxp
                        v_y += gyp
                        v_x_abs += abs(gxp)
                        v_y_abs += abs(gyp)
                        v_op += np.float64(vis) * v_alpha
            isect_grads[m, 0] = v_x
            isect_grads[m, 1] = v_y
            isect_grads[m, 2] = v_ca
            isect_grads[m, 3] = v_cb
            isect_grads[m, 4] = v_cc
            isect_grads[m, 5] = v_op
            isect_grads[m, 6] = v_x_abs
            isect_grads[m, 7] = v_y_abs
            for k in range(n_channels):
                isect_grads[m, GRAD_HEAD + k] = v_rgb[k]


@njit(cache=True, fastmath=False)
def reduce_isect_grads(isect_grads, flatten_ids, n_gaussians, gaussian_grads):
    """gaussian_grads[g] = sum of isect_grads[m] over m with flatten_ids[m] == g, float64, fixed order."""
    n_cols = isect_grads.shape[1]
    for m in range(flatten_ids.shape[0]):
        g = flatten_ids[m]
        for k in range(n_cols):
            gaussian_grads[g, k] += isect_grads[m, k]
