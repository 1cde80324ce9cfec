"""numba kernels of the fast CPU rasterizer (gsplat 1.5.3 ``RasterizeToPixels3DGS{Fwd,Bwd}.cu`` semantics).

Layout shared by the kernels (all arrays C-contiguous numpy):

- ``packed [M, PACK_HEAD + D] float32``: one row per intersection ``m`` (tile-sorted order), the Gaussian
  ``flatten_ids[m]`` gathered once so that a tile streams through contiguous memory:
  ``x, y, conic_a, conic_b, conic_c, opacity, extent_x, extent_y, sigma_cut, color[0..D)``. ``extent_*`` is a
  conservative half-size (px) of the ellipse where ``alpha >= alpha_threshold``: a tile only visits pixels inside
  it; a pixel with ``sigma > sigma_cut`` has ``alpha < alpha_threshold`` and is skipped before the exp.
- ``tile_offsets [C * tile_h * tile_w] int32``: first intersection of each tile (gsplat's ``isect_offsets``
  flattened); the last tile ends at ``M``.
- Per-pixel forward state ``T_final [C, H, W] float32`` (transmittance after the last contributor) and
  ``last_ids [C, H, W] int32`` (intersection index of the last contributor, -1 when none).
- ``isect_grads [M, GRAD_HEAD + D] float32``: per-intersection gradients written by the tile that owns the
  intersection (each intersection belongs to exactly one tile, so no write races), reduced to Gaussians by
  ``reduce_isect_grads`` in a fixed order per Gaussian (deterministic).

Kernel families: the 4x4-block kernels (``*_blocks``, 16 px tiles: ``constants.BLOCK_TILE_SIZE``) and the scalar
kernels (any other tile size); docs/rasterizer.md ("Two compositing families") measures why both stay. Every kernel
reads an intersection through ``_load_gaussian``; both families evaluate a Gaussian at a pixel through ``_gaussian_sigma`` and ``_alpha_at``
(the branch-free float32 ``exp_neg``), so they keep and skip the same (pixel, Gaussian) pairs; their colours differ
only by float32 (blocks) vs float64 (scalar forward) accumulation, up to about 2.4e-7.

The gsplat constants (alpha clamp, alpha threshold, transmittance threshold) are kernel ARGUMENTS, not globals:
numba freezes globals into its on-disk cache, and a cache keyed on this file alone would not see a change in
``constants.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# Layout constants (named once in constants.py). They shape the block kernels' arrays, so they are compile-time
# globals: numba's cache is keyed on THIS file, so after changing them there, delete render/__pycache__.
from .constants import BLOCK_SIZE, BLOCK_TILE_SIZE, BLOCKS_PER_TILE, LANES

# packed row: x, y, conic a, b, c, opacity, extent x, extent y, sigma cut, then D colour channels
PACK_X, PACK_Y, PACK_CONIC_A, PACK_CONIC_B, PACK_CONIC_C, PACK_OPACITY = 0, 1, 2, 3, 4, 5
PACK_EXTENT_X, PACK_EXTENT_Y, PACK_SIGMA_CUT = 6, 7, 8
PACK_HEAD = 9
# Pre-test margin on sigma: beyond log(opacity / threshold) + margin, alpha < threshold whatever expf rounds to,
# so such a pixel is skipped without calling exp (exactly as the full test would skip it).
SIGMA_CUT_MARGIN = 1e-3
# gradient row: v_x, v_y, v_conic a, b, c, v_opacity, |v_x|, |v_y| summed per pixel (absgrad), then D v_colors
GRAD_X, GRAD_Y, GRAD_CONIC_A, GRAD_CONIC_B, GRAD_CONIC_C, GRAD_OPACITY, GRAD_ABS_X, GRAD_ABS_Y = 0, 1, 2, 3, 4, 5, 6, 7
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
        packed[m, PACK_X] = means2d[g, 0]
        packed[m, PACK_Y] = means2d[g, 1]
        packed[m, PACK_CONIC_A] = a
        packed[m, PACK_CONIC_B] = b
        packed[m, PACK_CONIC_C] = c
        packed[m, PACK_OPACITY] = o
        # float64 on purpose: the extent must never be smaller than the float32 test it stands in for
        a64 = np.float64(a)
        b64 = np.float64(b)
        c64 = np.float64(c)
        det = a64 * c64 - b64 * b64
        if not (o >= alpha_threshold):
            # opacity * exp(-sigma) <= opacity < threshold for every sigma >= 0: no pixel passes
            ex = -1.0
            ey = -1.0
            sigma_cut = -1.0
        else:
            sigma_cut = math.log(np.float64(o) / np.float64(alpha_threshold)) + SIGMA_CUT_MARGIN
            if a64 > 0.0 and c64 > 0.0 and det > 0.0 and math.isfinite(det):
                ex = math.sqrt(2.0 * sigma_cut * c64 / det) * 1.001 + 1e-2
                ey = math.sqrt(2.0 * sigma_cut * a64 / det) * 1.001 + 1e-2
            else:
                ex = np.inf
                ey = np.inf
        packed[m, PACK_EXTENT_X] = ex
        packed[m, PACK_EXTENT_Y] = ey
        packed[m, PACK_SIGMA_CUT] = sigma_cut
        for k in range(n_channels):
            packed[m, PACK_HEAD + k] = colors[g, k]


@njit(inline="always")
def _gaussian_sigma(ca, cb, cc, dx, dy):
    """``sigma = 0.5 (a dx^2 + c dy^2) + b dx dy`` (float32) for the offset ``(dx, dy) = mean - pixel centre`` and the
    conic ``(a, b, c)``: the Gaussian's exponent at a pixel (gsplat's per-pixel evaluation). Every kernel uses it."""
    return _F32(0.5) * (ca * dx * dx + cc * dy * dy) + cb * dx * dy


@njit(inline="always")
def _alpha_at(opacity, sigma, max_alpha):
    """``(exp(-sigma), alpha = min(max_alpha, opacity exp(-sigma)))`` with the branch-free float32 ``exp_neg``, the
    same in the scalar and the block kernels (so both families take the same keep/skip decisions)."""
    vis = exp_neg(sigma)
    return vis, min(max_alpha, opacity * vis)


@njit(inline="always")
def _tile_geometry(tile, tiles_per_image, tile_width, tile_size, image_width, image_height):
    """Camera and pixel box ``[x0, x1) x [y0, y1)`` of flat tile index ``tile`` (camera-major, row-major tiles)."""
    cam = tile // tiles_per_image
    tile_in_image = tile - cam * tiles_per_image
    tile_y = tile_in_image // tile_width
    tile_x = tile_in_image - tile_y * tile_width
    x0 = tile_x * tile_size
    y0 = tile_y * tile_size
    return cam, x0, y0, min(x0 + tile_size, image_width), min(y0 + tile_size, image_height)


@njit(inline="always")
def _pixel_range(center, extent, pixel_offset, lo, hi):
    """Pixels ``p`` in ``[lo, hi)`` whose centre ``p + pixel_offset`` is within ``extent`` of ``center``: (first, end).

    Clamped in float64 before the integer conversion, so huge or infinite extents (elongated or degenerate
    Gaussians) give the whole range instead of an overflowed integer.
    """
    if not (extent >= 0.0):
        return lo, lo
    if not math.isfinite(center):
        return lo, hi
    first = max(np.ceil(np.float64(center) - np.float64(extent) - np.float64(pixel_offset)), np.float64(lo))
    last = min(np.floor(np.float64(center) + np.float64(extent) - np.float64(pixel_offset)), np.float64(hi - 1))
    if not (last >= first):
        return lo, lo
    return int(first), int(last) + 1


@njit(inline="always")
def _ellipse_rows(ca, cb, cc, sigma_cut):
    """Per-Gaussian coefficients of the row spans of the ellipse ``sigma <= sigma_cut`` (float64).

    With ``dx = x - px`` the row at offset ``dy`` holds ``dx`` in ``-(b/a) dy +- sqrt(2 cut / a - det / a^2 dy^2)``.
    Returns (bounded, 2 cut / a, det / a^2, b / a); ``bounded`` is False for a conic that is not positive definite.
    """
    a = np.float64(ca)
    b = np.float64(cb)
    det = a * np.float64(cc) - b * b
    if a > 0.0 and det > 0.0 and math.isfinite(det) and sigma_cut >= 0.0:
        return True, 2.0 * np.float64(sigma_cut) / a, det / (a * a), b / a
    return False, 0.0, 0.0, 0.0


@njit(inline="always")
def _row_range(bounded, k_cut, k_det, k_b, gx, dy, pixel_offset, lo, hi):
    """Pixels of ``[lo, hi)`` in one row whose centre may have ``sigma <= sigma_cut`` (conservative): (first, end)."""
    if not bounded:
        return lo, hi
    d = np.float64(dy)
    half_sq = k_cut - k_det * d * d
    if not (half_sq >= 0.0):
        return lo, lo
    half_w = math.sqrt(half_sq) * 1.001 + 1e-2
    center = np.float64(gx) + k_b * d - np.float64(pixel_offset)
    if not (math.isfinite(half_w) and math.isfinite(center)):
        return lo, hi
    first = max(np.ceil(center - half_w), np.float64(lo))
    last = min(np.floor(center + half_w), np.float64(hi - 1))
    if not (last >= first):
        return lo, lo
    return int(first), int(last) + 1


@njit(inline="always")
def _load_gaussian(packed, m, pixel_offset, x0, y0, x1, y1):
    """Intersection ``m``'s Gaussian and the pixels of the tile box ``[x0, x1) x [y0, y1)`` its ellipse's extent
    covers: (x, y, conic a, b, c, opacity, sigma_cut, (first, end) column, (first, end) row); a range is empty
    (end <= first) when the ellipse misses the tile. Every kernel's per-intersection prologue."""
    gx = packed[m, PACK_X]
    gy = packed[m, PACK_Y]
    j_first, j_end = _pixel_range(gx, packed[m, PACK_EXTENT_X], pixel_offset, x0, x1)
    i_first, i_end = _pixel_range(gy, packed[m, PACK_EXTENT_Y], pixel_offset, y0, y1)
    return (gx, gy, packed[m, PACK_CONIC_A], packed[m, PACK_CONIC_B], packed[m, PACK_CONIC_C], packed[m, PACK_OPACITY],
            packed[m, PACK_SIGMA_CUT], j_first, j_end, i_first, i_end)


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
    n_contrib,
):
    """Front-to-back compositing, one tile per task (fills render_colors [C,H,W,D], T_final, last_ids and
    n_contrib [C,H,W] int32, the number of Gaussians composited into each pixel).

    backgrounds [C,D] float32 (zeros when the caller has none: ``T * 0`` adds nothing).
    """
    n_isects = packed.shape[0]
    n_channels = packed.shape[1] - PACK_HEAD
    tiles_per_image = tile_height * tile_width
    n_tiles = n_cameras * tiles_per_image
    one = _F32(1.0)
    for tile in prange(n_tiles):
        cam, x0, y0, x1, y1 = _tile_geometry(tile, tiles_per_image, tile_width, tile_size, image_width, image_height)
        span_x = x1 - x0
        n_pix = span_x * (y1 - y0)
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1] if tile + 1 < n_tiles else n_isects

        T = np.ones(n_pix, dtype=np.float32)
        acc = np.zeros((n_pix, n_channels), dtype=np.float64)
        last = np.full(n_pix, -1, dtype=np.int32)
        count = np.zeros(n_pix, dtype=np.int32)
        done = np.zeros(n_pix, dtype=np.bool_)
        n_done = 0
        for m in range(start, end):
            if n_done == n_pix:
                break
            gx, gy, ca, cb, cc, op, sigma_cut, j_first, j_end, i_first, i_end = _load_gaussian(
                packed, m, pixel_offset, x0, y0, x1, y1)
            bounded, k_cut, k_det, k_b = _ellipse_rows(ca, cb, cc, sigma_cut)
            for i in range(i_first, i_end):
                dy = gy - (_F32(i) + pixel_offset)
                row_first, row_end = _row_range(bounded, k_cut, k_det, k_b, gx, dy, pixel_offset, j_first, j_end)
                row = (i - y0) * span_x - x0
                for j in range(row_first, row_end):
                    p = row + j
                    if done[p]:
                        continue
                    dx = gx - (_F32(j) + pixel_offset)
                    sigma = _gaussian_sigma(ca, cb, cc, dx, dy)
                    if sigma > sigma_cut:
                        continue
                    _, alpha = _alpha_at(op, sigma, max_alpha)
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
                    count[p] += 1
                    T[p] = next_T
        for i in range(y0, y1):
            for j in range(x0, x1):
                p = (i - y0) * span_x + (j - x0)
                t = T[p]
                T_final[cam, i, j] = t
                last_ids[cam, i, j] = last[p]
                n_contrib[cam, i, j] = count[p]
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
    for tile in prange(n_tiles):
        cam, x0, y0, x1, y1 = _tile_geometry(tile, tiles_per_image, tile_width, tile_size, image_width, image_height)
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
            gx, gy, ca, cb, cc, op, sigma_cut, j_first, j_end, i_first, i_end = _load_gaussian(
                packed, m, pixel_offset, x0, y0, x1, y1)
            bounded, k_cut, k_det, k_b = _ellipse_rows(ca, cb, cc, sigma_cut)
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
                row_first, row_end = _row_range(bounded, k_cut, k_det, k_b, gx, dy, pixel_offset, j_first, j_end)
                row = (i - y0) * span_x - x0
                for j in range(row_first, row_end):
                    p = row + j
                    if m > last[p]:
                        continue
                    dx = gx - (_F32(j) + pixel_offset)
                    sigma = _gaussian_sigma(ca, cb, cc, dx, dy)
                    if sigma > sigma_cut:
                        continue
                    vis, alpha = _alpha_at(op, sigma, max_alpha)
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
            isect_grads[m, GRAD_X] = v_x
            isect_grads[m, GRAD_Y] = v_y
            isect_grads[m, GRAD_CONIC_A] = v_ca
            isect_grads[m, GRAD_CONIC_B] = v_cb
            isect_grads[m, GRAD_CONIC_C] = v_cc
            isect_grads[m, GRAD_OPACITY] = v_op
            isect_grads[m, GRAD_ABS_X] = v_x_abs
            isect_grads[m, GRAD_ABS_Y] = v_y_abs
            for k in range(n_channels):
                isect_grads[m, GRAD_HEAD + k] = v_rgb[k]


@njit(parallel=True, cache=True, fastmath=False)
def reduce_isect_grads(isect_grads, flatten_ids, n_parts, sums, v_means2d, v_conics, v_opacities, v_abs, v_colors):
    """Per-Gaussian gradients: ``sums[g] = sum of isect_grads[m] over m with flatten_ids[m] == g`` in float64, in
    the serial order of m, then rounded into the per-input arrays v_means2d [G, 2], v_conics [G, 3],
    v_opacities [G], v_abs [G, 2] (absgrad; an empty array skips it), v_colors [G, D] (float32 or float64).

    ``sums`` [G, GRAD_HEAD + D] float64 must be zero. The Gaussians are cut into ``n_parts`` ranges, one per parallel
    task; each task scans every intersection and adds only its own Gaussians', so every Gaussian's sum has the same
    order whatever the thread count (deterministic), and each range is written out by the task that summed it.
    """
    n_gaussians = sums.shape[0]
    n_cols = isect_grads.shape[1]
    n_channels = v_colors.shape[1]
    want_abs = v_abs.shape[0] == n_gaussians
    for part in prange(n_parts):
        lo = n_gaussians * part // n_parts
        hi = n_gaussians * (part + 1) // n_parts
        for m in range(flatten_ids.shape[0]):
            g = flatten_ids[m]
            if g >= lo and g < hi:
                for k in range(n_cols):
                    sums[g, k] += isect_grads[m, k]
        for g in range(lo, hi):
            v_means2d[g, 0] = sums[g, GRAD_X]
            v_means2d[g, 1] = sums[g, GRAD_Y]
            v_conics[g, 0] = sums[g, GRAD_CONIC_A]
            v_conics[g, 1] = sums[g, GRAD_CONIC_B]
            v_conics[g, 2] = sums[g, GRAD_CONIC_C]
            v_opacities[g] = sums[g, GRAD_OPACITY]
            if want_abs:
                v_abs[g, 0] = sums[g, GRAD_ABS_X]
                v_abs[g, 1] = sums[g, GRAD_ABS_Y]
            for k in range(n_channels):
                v_colors[g, k] = sums[g, GRAD_HEAD + k]


# ------------------------------------------------------------------------------------------------------------------
# Lane utilities for the vectorized 16 px tile kernels below: 16 pixels are processed as 16 lanes without branches
# (LLVM turns the lane loops into AVX2 code), and the Gaussian's exp is the branch-free ``exp_neg``. Decisions (skip,
# stop) are the same per-pixel tests as the scalar kernels above.
# ------------------------------------------------------------------------------------------------------------------

_LOG2E = np.float32(1.4426950408889634)
# ln 2 split in a high part exact in float32 and a low remainder (Cody-Waite range reduction)
_LN2_HI = np.float32(0.693359375)
_LN2_LO = np.float32(-2.12194440e-4)
# exp(-s) is only needed for s <= sigma_cut = log(opacity / alpha_threshold) + margin < 6; larger s is masked out
_EXP_NEG_MAX = np.float32(12.0)


@njit(inline="always")
def exp_neg(s):
    """``exp(-s)`` in float32 arithmetic only (no libm call, no branch: vectorizable), ``s`` clamped to [0, 12].

    ``s = n ln2 + r`` with integer ``n`` and ``|r| <= ln2 / 2``; ``exp(-r)`` by its degree-7 Taylor polynomial
    (truncation < 6e-9), ``2^-n`` by exact power-of-two factors. Relative error <= 1.1e-7 (~2 float32 ulp) on
    [0, 12], like gsplat's ``__expf`` an approximation of a few ulp.
    """
    s = min(max(s, _F32(0.0)), _EXP_NEG_MAX)
    nf = np.floor(s * _LOG2E + _F32(0.5))
    r = (nf * _LN2_HI - s) + nf * _LN2_LO
    p = _F32(1.0 / 5040.0)
    p = p * r + _F32(1.0 / 720.0)
    p = p * r + _F32(1.0 / 120.0)
    p = p * r + _F32(1.0 / 24.0)
    p = p * r + _F32(1.0 / 6.0)
    p = p * r + _F32(0.5)
    p = p * r + _F32(1.0)
    p = p * r + _F32(1.0)
    # 2^-n for n in [0, 17] from its binary digits, every factor exact
    c = nf >= _F32(16.0)
    p = p * (_F32(2.0**-16) if c else _F32(1.0))
    nf = nf - (_F32(16.0) if c else _F32(0.0))
    c = nf >= _F32(8.0)
    p = p * (_F32(2.0**-8) if c else _F32(1.0))
    nf = nf - (_F32(8.0) if c else _F32(0.0))
    c = nf >= _F32(4.0)
    p = p * (_F32(2.0**-4) if c else _F32(1.0))
    nf = nf - (_F32(4.0) if c else _F32(0.0))
    c = nf >= _F32(2.0)
    p = p * (_F32(0.25) if c else _F32(1.0))
    nf = nf - (_F32(2.0) if c else _F32(0.0))
    c = nf >= _F32(1.0)
    return p * (_F32(0.5) if c else _F32(1.0))


# ------------------------------------------------------------------------------------------------------------------
# 4x4-block kernels for 16 px tiles: a tile is 16 blocks of 4x4 pixels and the 16 pixels of one block are the 16
# branch-free lanes. A Gaussian visits only the blocks that its ellipse's row spans touch (the union of the spans of
# the block's 4 rows), so a small Gaussian wastes far fewer lanes than with whole 16 px rows. State is [block, lane]:
# block ``b = (r // 4) * 4 + c // 4``, lane ``l = (r % 4) * 4 + c % 4`` for the pixel at tile row r, column c.
# Per-pixel arithmetic and tests are exactly those of the scalar kernels above.
# ------------------------------------------------------------------------------------------------------------------

BLOCK = BLOCK_SIZE


@njit(inline="always")
def _block_cols(bounded, k_cut, k_det, k_b, gx, gy, pixel_offset, i_a, i_b, j_first, j_end):
    """Union over rows ``[i_a, i_b)`` of their row spans within ``[j_first, j_end)``: (first, end), empty if
    end <= first."""
    cf = j_end
    ce = j_first
    for i in range(i_a, i_b):
        dy = gy - (_F32(i) + pixel_offset)
        rf, re = _row_range(bounded, k_cut, k_det, k_b, gx, dy, pixel_offset, j_first, j_end)
        if re > rf:
            cf = min(cf, rf)
            ce = max(ce, re)
    return cf, ce


@njit(inline="always")
def _block_tables(x0, y0, pixel_offset):
    """Pixel-centre coordinates per (block column, lane) and (block row, lane), float32 exactly as the scalar kernels."""
    px = np.empty((BLOCK, LANES), dtype=np.float32)
    py = np.empty((BLOCK, LANES), dtype=np.float32)
    for q in range(BLOCK):
        for lane in range(LANES):
            px[q, lane] = _F32(x0 + BLOCK * q + (lane % BLOCK)) + pixel_offset
            py[q, lane] = _F32(y0 + BLOCK * q + (lane // BLOCK)) + pixel_offset
    return px, py


@njit(parallel=True, cache=True, fastmath=False)
def rasterize_fwd_blocks(
    packed,
    tile_offsets,
    backgrounds,
    n_cameras,
    image_height,
    image_width,
    tile_height,
    tile_width,
    pixel_offset,
    max_alpha,
    alpha_threshold,
    transmittance_threshold,
    render_colors,
    T_final,
    last_ids,
    n_contrib,
):
    """``rasterize_fwd`` for 16 px tiles with 4x4-pixel blocks as the 16 lanes (same outputs)."""
    n_isects = packed.shape[0]
    n_channels = packed.shape[1] - PACK_HEAD
    tiles_per_image = tile_height * tile_width
    n_tiles = n_cameras * tiles_per_image
    one = _F32(1.0)
    zero = _F32(0.0)
    for tile in prange(n_tiles):
        cam, x0, y0, x1, y1 = _tile_geometry(tile, tiles_per_image, tile_width, BLOCK_TILE_SIZE, image_width,
                                               image_height)
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1] if tile + 1 < n_tiles else n_isects
        T = np.ones((BLOCKS_PER_TILE, LANES), dtype=np.float32)
        acc = np.zeros((n_channels, BLOCKS_PER_TILE, LANES), dtype=np.float32)
        last = np.full((BLOCKS_PER_TILE, LANES), -1, dtype=np.int32)
        count = np.zeros((BLOCKS_PER_TILE, LANES), dtype=np.float32)
        # 1 while the pixel composites; 0 once done (and for lanes outside the image)
        live = np.zeros((BLOCKS_PER_TILE, LANES), dtype=np.float32)
        # live lanes per block and in the tile: a block with none is skipped whole (its lanes would change nothing)
        block_live = np.zeros(BLOCKS_PER_TILE, dtype=np.int32)
        for r in range(y1 - y0):
            for c in range(x1 - x0):
                b = (r // BLOCK) * BLOCK + c // BLOCK
                live[b, (r % BLOCK) * BLOCK + c % BLOCK] = one
                block_live[b] += 1
        tile_live = (y1 - y0) * (x1 - x0)
        px, py = _block_tables(x0, y0, pixel_offset)
        vis = np.empty(LANES, dtype=np.float32)
        for m in range(start, end):
            if tile_live == 0:
                break
            gx, gy, ca, cb, cc, op, sigma_cut, j_first, j_end, i_first, i_end = _load_gaussian(
                packed, m, pixel_offset, x0, y0, x1, y1)
            if j_end <= j_first or i_end <= i_first:
                continue
            bounded, k_cut, k_det, k_b = _ellipse_rows(ca, cb, cc, sigma_cut)
            mi = np.int32(m)
            c0 = packed[m, PACK_HEAD] if n_channels == 3 else zero
            c1 = packed[m, PACK_HEAD + 1] if n_channels == 3 else zero
            c2 = packed[m, PACK_HEAD + 2] if n_channels == 3 else zero
            for br in range((i_first - y0) // BLOCK, (i_end - 1 - y0) // BLOCK + 1):
                i_a = max(i_first, y0 + BLOCK * br)
                i_b = min(i_end, y0 + BLOCK * br + BLOCK)
                cf, ce = _block_cols(bounded, k_cut, k_det, k_b, gx, gy, pixel_offset, i_a, i_b, j_first, j_end)
                if ce <= cf:
                    continue
                for bc in range((cf - x0) // BLOCK, (ce - 1 - x0) // BLOCK + 1):
                    b = br * BLOCK + bc
                    if block_live[b] == 0:
                        continue
                    n_stop = 0
                    for lane in range(LANES):
                        dx = gx - px[bc, lane]
                        dy = gy - py[br, lane]
                        sigma = _gaussian_sigma(ca, cb, cc, dx, dy)
                        _, alpha = _alpha_at(op, sigma, max_alpha)
                        t = T[b, lane]
                        next_t = t * (one - alpha)
                        ok = ((sigma >= zero) & (sigma <= sigma_cut) & (alpha >= alpha_threshold)
                              & (live[b, lane] > zero))
                        use = ok & (next_t > transmittance_threshold)
                        stop = ok & (next_t <= transmittance_threshold)
                        v = alpha * t if use else zero
                        vis[lane] = v
                        if n_channels == 3:  # RGB (training): accumulated here, no second pass over the lanes
                            acc[0, b, lane] += c0 * v
                            acc[1, b, lane] += c1 * v
                            acc[2, b, lane] += c2 * v
                        T[b, lane] = next_t if use else t
                        last[b, lane] = mi if use else last[b, lane]
                        count[b, lane] += one if use else zero
                        live[b, lane] = zero if stop else live[b, lane]
                        n_stop += 1 if stop else 0
                    block_live[b] -= n_stop
                    tile_live -= n_stop
                    if n_channels != 3:
                        for k in range(n_channels):
                            ck = packed[m, PACK_HEAD + k]
                            for lane in range(LANES):
                                acc[k, b, lane] += ck * vis[lane]
        for i in range(y0, y1):
            for j in range(x0, x1):
                r = i - y0
                c = j - x0
                b = (r // BLOCK) * BLOCK + c // BLOCK
                lane = (r % BLOCK) * BLOCK + c % BLOCK
                t = T[b, lane]
                T_final[cam, i, j] = t
                last_ids[cam, i, j] = last[b, lane]
                n_contrib[cam, i, j] = np.int32(count[b, lane])
                for k in range(n_channels):
                    render_colors[cam, i, j, k] = acc[k, b, lane] + t * backgrounds[cam, k]


@njit(parallel=True, cache=True, fastmath=False, error_model="numpy")
def rasterize_bwd_blocks(
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
    tile_height,
    tile_width,
    pixel_offset,
    max_alpha,
    alpha_threshold,
    isect_grads,
):
    """``rasterize_bwd`` for 16 px tiles with 4x4-pixel blocks as the 16 lanes (same outputs).

    Per Gaussian, each gradient is summed per lane over the visited blocks (in block order), then over the 16 lanes
    in float64 by a fixed pairwise tree: deterministic whatever the thread count.
    """
    n_isects = packed.shape[0]
    n_channels = packed.shape[1] - PACK_HEAD
    tiles_per_image = tile_height * tile_width
    n_tiles = n_cameras * tiles_per_image
    half = _F32(0.5)
    one = _F32(1.0)
    zero = _F32(0.0)
    for tile in prange(n_tiles):
        cam, x0, y0, x1, y1 = _tile_geometry(tile, tiles_per_image, tile_width, BLOCK_TILE_SIZE, image_width,
                                               image_height)
        start = tile_offsets[tile]
        end = tile_offsets[tile + 1] if tile + 1 < n_tiles else n_isects
        if end <= start:
            continue
        T = np.ones((BLOCKS_PER_TILE, LANES), dtype=np.float32)
        last = np.full((BLOCKS_PER_TILE, LANES), -1, dtype=np.int32)
        v_c = np.zeros((n_channels, BLOCKS_PER_TILE, LANES), dtype=np.float32)
        alpha_term = np.zeros((BLOCKS_PER_TILE, LANES), dtype=np.float32)
        buffer = np.zeros((n_channels, BLOCKS_PER_TILE, LANES), dtype=np.float32)
        tile_last = -1
        for i in range(y0, y1):
            for j in range(x0, x1):
                r = i - y0
                c = j - x0
                b = (r // BLOCK) * BLOCK + c // BLOCK
                lane = (r % BLOCK) * BLOCK + c % BLOCK
                t = T_final[cam, i, j]
                T[b, lane] = t
                lp = last_ids[cam, i, j]
                last[b, lane] = lp
                if lp > tile_last:
                    tile_last = lp
                bg_dot = zero
                for k in range(n_channels):
                    v = v_render_colors[cam, i, j, k]
                    v_c[k, b, lane] = v
                    bg_dot += backgrounds[cam, k] * v
                # d(out)/d(alpha) terms that do not depend on the Gaussian: T_final * (v_alpha_out - <bg, v_color>)
                alpha_term[b, lane] = t * (v_render_alphas[cam, i, j] - bg_dot)
        px, py = _block_tables(x0, y0, pixel_offset)
        # one block's per-lane values (vis, T, 1 / (1 - alpha), valid, d out / d alpha), in one allocation
        scratch = np.empty((5, LANES), dtype=np.float32)
        # per-lane sums over the blocks of one Gaussian: v_x, v_y, v_a, v_b, v_c, v_opacity, |v_x|, |v_y|, v_rgb
        sums = np.empty((GRAD_HEAD + n_channels, LANES), dtype=np.float32)
        pair_sums = np.empty(LANES // 2, dtype=np.float64)
        for m in range(min(tile_last, end - 1), start - 1, -1):
            gx, gy, ca, cb, cc, op, sigma_cut, j_first, j_end, i_first, i_end = _load_gaussian(
                packed, m, pixel_offset, x0, y0, x1, y1)
            if j_end <= j_first or i_end <= i_first:
                continue
            bounded, k_cut, k_det, k_b = _ellipse_rows(ca, cb, cc, sigma_cut)
            sums[:, :] = zero
            mi = np.int32(m)
            for br in range((i_first - y0) // BLOCK, (i_end - 1 - y0) // BLOCK + 1):
                i_a = max(i_first, y0 + BLOCK * br)
                i_b = min(i_end, y0 + BLOCK * br + BLOCK)
                cf, ce = _block_cols(bounded, k_cut, k_det, k_b, gx, gy, pixel_offset, i_a, i_b, j_first, j_end)
                if ce <= cf:
                    continue
                for bc in range((cf - x0) // BLOCK, (ce - 1 - x0) // BLOCK + 1):
                    b = br * BLOCK + bc
                    for lane in range(LANES):
                        dx = gx - px[bc, lane]
                        dy = gy - py[br, lane]
                        sigma = _gaussian_sigma(ca, cb, cc, dx, dy)
                        vis, alpha = _alpha_at(op, sigma, max_alpha)
                        valid = ((mi <= last[b, lane]) & (sigma >= zero) & (sigma <= sigma_cut)
                                 & (alpha >= alpha_threshold))
                        ra = one / (one - alpha)
                        t = T[b, lane] * ra
                        T[b, lane] = t if valid else T[b, lane]
                        scratch[0, lane] = vis
                        scratch[1, lane] = t
                        scratch[2, lane] = ra
                        scratch[3, lane] = one if valid else zero
                        scratch[4, lane] = alpha_term[b, lane] * ra
                    for k in range(n_channels):
                        ck = packed[m, PACK_HEAD + k]
                        for lane in range(LANES):
                            on = scratch[3, lane] > zero
                            t = scratch[1, lane]
                            fac = min(max_alpha, op * scratch[0, lane]) * t
                            vk = v_c[k, b, lane]
                            sums[GRAD_HEAD + k, lane] += fac * vk if on else zero
                            scratch[4, lane] += (ck * t - buffer[k, b, lane] * scratch[2, lane]) * vk
                            buffer[k, b, lane] += ck * fac if on else zero
                    for lane in range(LANES):
                        dx = gx - px[bc, lane]
                        dy = gy - py[br, lane]
                        vis = scratch[0, lane]
                        v_alpha = scratch[4, lane]
                        # gsplat leaves opacity and geometry gradients at 0 where the alpha clamp is active
                        unclamped = (scratch[3, lane] > zero) & (op * vis <= max_alpha)
                        v_sigma = -op * vis * v_alpha if unclamped else zero
                        g_x = v_sigma * (ca * dx + cb * dy)
                        g_y = v_sigma * (cb * dx + cc * dy)
                        sums[0, lane] += g_x
                        sums[1, lane] += g_y
                        sums[2, lane] += half * v_sigma * dx * dx
                        sums[3, lane] += v_sigma * dx * dy
                        sums[4, lane] += half * v_sigma * dy * dy
                        sums[5, lane] += vis * v_alpha if unclamped else zero
                        sums[6, lane] += abs(g_x)
                        sums[7, lane] += abs(g_y)
            # pairwise over the lanes in float64, a fixed tree: element-wise (vectorizable) and deterministic
            for q in range(GRAD_HEAD + n_channels):
                for lane in range(LANES // 2):
                    pair_sums[lane] = np.float64(sums[q, lane]) + np.float64(sums[q, lane + LANES // 2])
                for lane in range(LANES // 4):
                    pair_sums[lane] = pair_sums[lane] + pair_sums[lane + LANES // 4]
                isect_grads[m, q] = (pair_sums[0] + pair_sums[2]) + (pair_sums[1] + pair_sums[3])
