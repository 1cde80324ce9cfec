"""numba kernels of the fused CPU D-SSIM (:func:`kc_splatfacto.losses.photometric.dssim`): kornia's SSIM, forward and
analytic backward, without torch's per-op overhead and oneDNN's layout copies around depthwise convolutions.

Arrays are C-contiguous numpy ``[P, H, W]`` planes (P = B * C), float32 or float64 (numba compiles one version per
dtype). The blur is kornia's ``filter2d_separable``: reflect padding (``torch.nn.functional.pad(mode="reflect")``:
index -1 reads 1, index W reads W - 2) and a correlation with the 1D window ``taps`` [K], first along W, then along H.

Forward (``ssim_moments`` then ``ssim_partials``): the five moments ``mu_x, mu_y, E[x^2], E[y^2], E[xy]``, the SSIM
map ``s = A B / (Cd D + eps)`` with ``A = 2 mu_x mu_y + c1``, ``B = 2 (E[xy] - mu_x mu_y) + c2``,
``Cd = mu_x^2 + mu_y^2 + c1``, ``D = E[x^2] - mu_x^2 + E[y^2] - mu_y^2 + c2`` (kornia's arithmetic), per-row sums of
``s`` (summed in a fixed order by the caller: the mean does not depend on the thread count), and the three partials
``ds/dmu_x``, ``ds/dE[x^2]``, ``ds/dE[xy]`` per pixel, kept for the backward.

Backward (``ssim_input_grad``): the blur's adjoint applied to the partials (``blur_cols_adjoint`` then
``blur_rows_adjoint``: a full correlation of the zero-extended gradient with the flipped, here symmetric, window, then
the padded border folded back onto the pixels it mirrored), then ``dx = a + 2 x b_xx + y b_xy``.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# moment rows of the stacked [N_MOMENTS, P, H, W] array
MOM_X, MOM_Y, MOM_XX, MOM_YY, MOM_XY = 0, 1, 2, 3, 4
N_MOMENTS = 5
# partial rows of the stacked [N_PARTIALS, P, H, W] array: ds/dmu_x, ds/dE[x^2], ds/dE[xy]
PART_MU, PART_XX, PART_XY = 0, 1, 2
N_PARTIALS = 3


@njit(inline="always")
def _reflect(q, n):
    """torch's 'reflect' index (the edge sample not repeated) for ``-n < q < 2n - 1``."""
    if q < 0:
        return -q
    if q > n - 1:
        return 2 * (n - 1) - q
    return q


@njit(inline="always")
def _plane_row(row, height):
    """(plane, row within the plane) of flat row index ``row`` over [S, H] (the kernels' parallel unit)."""
    plane = row // height
    return plane, row - plane * height


@njit(inline="always")
def _add_scaled_row(out, s, i, k, src, q):
    """``out[s, i, :] += k * src[s, q, :]``."""
    for j in range(out.shape[2]):
        out[s, i, j] += k * src[s, q, j]


@njit(parallel=True, cache=True)
def blur_rows(src, taps, out):
    """``out[s, i, :]`` = reflect-padded correlation of ``src[s, i, :]`` with ``taps`` along W. src, out [S, H, W]."""
    n_planes, height, width = src.shape
    n_taps = taps.shape[0]
    radius = n_taps // 2
    for row in prange(n_planes * height):
        s, i = _plane_row(row, height)
        padded = np.empty(width + 2 * radius, dtype=src.dtype)
        for q in range(width + 2 * radius):
            padded[q] = src[s, i, _reflect(q - radius, width)]
        for j in range(width):
            out[s, i, j] = 0.0
        for t in range(n_taps):
            k = taps[t]
            for j in range(width):
                out[s, i, j] += k * padded[j + t]


@njit(parallel=True, cache=True)
def blur_cols(src, taps, out):
    """``out[s, :, :]`` = reflect-padded correlation of ``src[s]`` with ``taps`` along H (whole rows at a time)."""
    n_planes, height, width = src.shape
    n_taps = taps.shape[0]
    radius = n_taps // 2
    for row in prange(n_planes * height):
        s, i = _plane_row(row, height)
        for j in range(width):
            out[s, i, j] = 0.0
        for t in range(n_taps):
            k = taps[t]
            _add_scaled_row(out, s, i, k, src, _reflect(i + t - radius, height))


@njit(parallel=True, cache=True)
def blur_rows_adjoint(grad, taps, out):
    """Adjoint of :func:`blur_rows`: ``out`` [S, H, W] = the gradient w.r.t. its ``src`` given ``grad`` [S, H, W]."""
    n_planes, height, width = grad.shape
    n_taps = taps.shape[0]
    radius = n_taps // 2
    n_padded = width + 2 * radius
    for row in prange(n_planes * height):
        s, i = _plane_row(row, height)
        # the gradient w.r.t. the padded row: padded[p] = sum_t taps[t] grad[p - t] (grad is 0 outside [0, W))
        zero_ext = np.zeros(width + 2 * (n_taps - 1), dtype=grad.dtype)
        for j in range(width):
            zero_ext[j + n_taps - 1] = grad[s, i, j]
        padded = np.zeros(n_padded, dtype=grad.dtype)
        for t in range(n_taps):
            k = taps[t]
            for p in range(n_padded):
                padded[p] += k * zero_ext[p - t + n_taps - 1]
        # fold: every padded position p read the pixel reflect(p - radius)
        for j in range(width):
            out[s, i, j] = padded[j + radius]
        for p in range(radius):
            out[s, i, _reflect(p - radius, width)] += padded[p]
        for p in range(width + radius, n_padded):
            out[s, i, _reflect(p - radius, width)] += padded[p]


@njit(parallel=True, cache=True)
def blur_cols_adjoint(grad, taps, out):
    """Adjoint of :func:`blur_cols`: ``out`` [S, H, W] = the gradient w.r.t. its ``src`` given ``grad`` [S, H, W].

    Gathered per output row (no write races): row ``q`` collects ``taps[t] grad[i]`` over every (i, t) whose padded
    read ``i + t - radius`` mirrors onto ``q``: directly, or through the top or bottom reflection.
    """
    n_planes, height, width = grad.shape
    n_taps = taps.shape[0]
    radius = n_taps // 2
    for row in prange(n_planes * height):
        s, q = _plane_row(row, height)
        for j in range(width):
            out[s, q, j] = 0.0
        for t in range(n_taps):
            k = taps[t]
            # padded index i + t - radius equal to q, to -q (top mirror, q > 0) or to 2 (H - 1) - q (bottom, q < H - 1)
            i = q - t + radius
            if 0 <= i < height:
                _add_scaled_row(out, s, q, k, grad, i)
            i = -q - t + radius
            if q > 0 and 0 <= i < height:
                _add_scaled_row(out, s, q, k, grad, i)
            i = 2 * (height - 1) - q - t + radius
            if q < height - 1 and 0 <= i < height:
                _add_scaled_row(out, s, q, k, grad, i)


@njit(parallel=True, cache=True)
def stack_moments_input(x, y, out):
    """``out`` [5, P, H, W] = x, y, x^2, y^2, x y (the images whose blurs are the moments)."""
    n_planes, height, width = x.shape
    for row in prange(n_planes * height):
        s, i = _plane_row(row, height)
        for j in range(width):
            a = x[s, i, j]
            b = y[s, i, j]
            out[MOM_X, s, i, j] = a
            out[MOM_Y, s, i, j] = b
            out[MOM_XX, s, i, j] = a * a
            out[MOM_YY, s, i, j] = b * b
            out[MOM_XY, s, i, j] = a * b


@njit(parallel=True, cache=True)
def ssim_partials(moments, c1, c2, eps, row_sums, partials):
    """SSIM per pixel from the blurred moments [5, P, H, W]: fills ``row_sums`` [P * H] (sum of the map over each
    row, float64) and ``partials`` [3, P, H, W] (ds/dmu_x, ds/dE[x^2], ds/dE[xy])."""
    n_planes, height, width = moments.shape[1:]
    for row in prange(n_planes * height):
        s, i = _plane_row(row, height)
        total = 0.0
        for j in range(width):
            mu_x = moments[MOM_X, s, i, j]
            mu_y = moments[MOM_Y, s, i, j]
            mu_xy = mu_x * mu_y
            mu_x_sq = mu_x * mu_x
            mu_y_sq = mu_y * mu_y
            sigma_x_sq = moments[MOM_XX, s, i, j] - mu_x_sq
            sigma_y_sq = moments[MOM_YY, s, i, j] - mu_y_sq
            sigma_xy = moments[MOM_XY, s, i, j] - mu_xy
            # v + v is 2 v exactly, in the arrays' own precision (a float literal would promote float32 to float64)
            num_a = (mu_xy + mu_xy) + c1
            num_b = (sigma_xy + sigma_xy) + c2
            den_c = mu_x_sq + mu_y_sq + c1
            den_d = sigma_x_sq + sigma_y_sq + c2
            den = den_c * den_d + eps
            value = (num_a * num_b) / den
            total += np.float64(value)
            # d s / d(A, B, Cd, D), then through mu_x (A: 2 mu_y, B: -2 mu_y, Cd: 2 mu_x, D: -2 mu_x), E[x^2]
            # (D: 1) and E[xy] (B: 2)
            d_a = num_b / den
            d_b = num_a / den
            d_c = -value * den_d / den
            d_d = -value * den_c / den
            g_mu = mu_y * (d_a - d_b) + mu_x * (d_c - d_d)
            partials[PART_MU, s, i, j] = g_mu + g_mu
            partials[PART_XX, s, i, j] = d_d
            partials[PART_XY, s, i, j] = d_b + d_b
        row_sums[row] = total


@njit(parallel=True, cache=True)
def ssim_input_grad(blurred_partials, x, y, scale, out):
    """``out`` [P, H, W] = scale * (a + 2 x b_xx + y b_xy) from the adjoint-blurred partials (a, b_xx, b_xy)."""
    n_planes, height, width = x.shape
    for row in prange(n_planes * height):
        s, i = _plane_row(row, height)
        for j in range(width):
            out[s, i, j] = scale * (blurred_partials[PART_MU, s, i, j]
                                    + (x[s, i, j] + x[s, i, j]) * blurred_partials[PART_XX, s, i, j]
                                    + y[s, i, j] * blurred_partials[PART_XY, s, i, j])
