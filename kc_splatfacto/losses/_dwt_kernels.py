"""numba kernels of the CPU wavelet losses: one separable DWT level with its adjoint, and the band moments with theirs.

Arrays are C-contiguous numpy arrays, float32 or float64 (numba compiles one version per dtype); every sum runs in
float64 and is rounded once, so a float32 image's coefficients are closer to the exact ones than a float32
convolution's. The level kernels are parallel over image or output rows, the moment kernels over (plane, chunk of
pixels) with the partial sums combined in chunk order, the L1 kernels serial: nothing depends on the thread count.
The moment and L1 sums may be reassociated by the compiler (vectorized reductions); the order is still fixed by the
compiled code.

**Level** (``level_rows`` then ``level_cols``). One level of x [N, H, W] is the valid stride-2 correlation of the
extended image with the four separable filters (lo/hi along H times lo/hi along W; ``taps_lo`` / ``taps_hi`` [L] are
the correlation taps, i.e. the reversed decomposition filters). ``rows`` / ``cols`` are the extension's index maps
(``wavelets._extension_index``: extended position p reads image row ``rows[p]``), so the boundary mode is in the maps
and the kernels only filter: first along W on the H image rows (``low`` / ``high`` [N, H, w], float64), then along H
through ``rows``. Output (cA, cH, cV, cD) in PyWavelets' order: cH = hi along H of the W-low rows, cV = lo along H of
the W-high rows.

**Level adjoint** (``level_cols_adjoint`` then ``level_rows_adjoint``), gathered per image row, no write races: image
row t collects every (output row r, tap i) whose extended row 2 r + i reads t (``row_ptr`` / ``row_pos``: the
extended positions of each image row, a CSR inverse of ``rows``), then scatters within its own row through ``cols``.

**Band moments** (``band_moments``, ``band_moments_adjoint``). For the three detail bands b of a plane, with
z = (x - mean(x)) s (s = the plane's inverse RMS coefficient magnitude): m2 = mean z^2, m4 = mean z^4 and the cross
sums z_a . z_b / (P - 1). The adjoint of given (dm2, dm4, dC) is dz_a = z_a (c2_a + c4_a z_a^2) + sum_b S_ab z_b with
c2 = 2 dm2 s / P, c4 = 4 dm4 s / P, S = (dC + dC^T) s / (P - 1); then dx = dz - mean(dz).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

# channel rows of a level's [N, 4, h, w] output
BAND_A, BAND_H, BAND_V, BAND_D = 0, 1, 2, 3
N_LEVEL_BANDS = 4
N_DETAIL_BANDS = 3


@njit(inline="always")
def _plane_row(row, height):
    """(plane, row within the plane) of flat row index ``row`` over [N, H] (the kernels' parallel unit)."""
    plane = row // height
    return plane, row - plane * height


@njit(inline="always")
def _split_phases(values, even, odd):
    """even[k] = values[2 k], odd[k] = values[2 k + 1] (float64), as far as the buffers reach."""
    for k in range(even.shape[0]):
        even[k] = values[2 * k]
    for k in range(odd.shape[0]):
        odd[k] = values[2 * k + 1]


@njit(inline="always")
def _tap_phase(j, even, odd):
    """(phase buffer, offset) that tap j of a stride-2 correlation reads: ``phase[s + offset]`` for output s."""
    return (even if j % 2 == 0 else odd), j // 2


@njit(parallel=True, cache=True)
def level_rows(image, cols, taps_lo, taps_hi, low, high):
    """W pass: ``low`` / ``high`` [N, H, w] (float64) = each image row, extended through ``cols``, correlated with
    ``taps_lo`` / ``taps_hi`` at stride 2. image [N, H, W].

    Polyphase: the extended row is split into its even and odd samples, so tap j reads a contiguous run
    (``phase_j[s + j // 2]``) and the loop over s vectorizes.
    """
    n_planes, height, _ = image.shape
    n_taps = taps_lo.shape[0]
    width_out = low.shape[2]
    n_phase = width_out + n_taps // 2 - 1  # tap j reads phase[s + j // 2], s < w
    for row in prange(n_planes * height):
        n, r = _plane_row(row, height)
        extended = np.empty(cols.shape[0])
        even = np.empty(n_phase)
        odd = np.empty(n_phase)
        for q in range(cols.shape[0]):
            extended[q] = image[n, r, cols[q]]
        _split_phases(extended, even, odd)
        for s in range(width_out):
            low[n, r, s] = 0.0
            high[n, r, s] = 0.0
        for j in range(n_taps):
            phase, offset = _tap_phase(j, even, odd)
            for s in range(width_out):
                value = phase[s + offset]
                low[n, r, s] += taps_lo[j] * value
                high[n, r, s] += taps_hi[j] * value


@njit(parallel=True, cache=True)
def level_cols(low, high, rows, taps_lo, taps_hi, approx, detail):
    """H pass: ``approx`` [N, 1, h, w] = cA and ``detail`` [N, 3, h, w] = (cH, cV, cD) from the W pass's rows
    (whole rows at a time: output row r adds tap i times W-pass row ``rows[2 r + i]``)."""
    n_planes, _, height_out, width_out = detail.shape
    n_taps = taps_lo.shape[0]
    for row in prange(n_planes * height_out):
        n, r = _plane_row(row, height_out)
        acc = np.zeros((N_LEVEL_BANDS, width_out))
        for i in range(n_taps):
            q = rows[2 * r + i]
            tap_lo = taps_lo[i]
            tap_hi = taps_hi[i]
            for s in range(width_out):
                lo_value = low[n, q, s]
                hi_value = high[n, q, s]
                acc[BAND_A, s] += tap_lo * lo_value
                acc[BAND_H, s] += tap_hi * lo_value
                acc[BAND_V, s] += tap_lo * hi_value
                acc[BAND_D, s] += tap_hi * hi_value
        for s in range(width_out):
            approx[n, 0, r, s] = acc[BAND_A, s]
            detail[n, 0, r, s] = acc[BAND_H, s]
            detail[n, 1, r, s] = acc[BAND_V, s]
            detail[n, 2, r, s] = acc[BAND_D, s]


@njit(parallel=True, cache=True)
def level_cols_adjoint(grad_approx, grad_detail, row_ptr, row_pos, taps_lo, taps_hi, low_grad, high_grad):
    """Adjoint of :func:`level_cols`: ``low_grad`` / ``high_grad`` [N, H, w] (float64, written) from the gradients of
    cA [N, 1, h, w] and (cH, cV, cD) [N, 3, h, w]. Image row t gathers over its extended positions
    ``row_pos[row_ptr[t]:row_ptr[t + 1]]`` (those the output reads)."""
    n_planes, height, width_out = low_grad.shape
    height_out = grad_detail.shape[2]
    n_taps = taps_lo.shape[0]
    for row in prange(n_planes * height):
        n, t = _plane_row(row, height)
        for s in range(width_out):
            low_grad[n, t, s] = 0.0
            high_grad[n, t, s] = 0.0
        for k in range(row_ptr[t], row_ptr[t + 1]):
            p = row_pos[k]
            # outputs r whose window [2 r, 2 r + L) holds p
            first = max(0, (p - n_taps + 2) // 2)
            last = min(height_out - 1, p // 2)
            for r in range(first, last + 1):
                tap_lo = taps_lo[p - 2 * r]
                tap_hi = taps_hi[p - 2 * r]
                for s in range(width_out):
                    low_grad[n, t, s] += (tap_lo * np.float64(grad_approx[n, 0, r, s])
                                          + tap_hi * np.float64(grad_detail[n, 0, r, s]))
                    high_grad[n, t, s] += (tap_lo * np.float64(grad_detail[n, 1, r, s])
                                           + tap_hi * np.float64(grad_detail[n, 2, r, s]))


@njit(parallel=True, cache=True)
def level_rows_adjoint(low_grad, high_grad, cols, taps_lo, taps_hi, grad_image):
    """Adjoint of :func:`level_rows`: ``grad_image`` [N, H, W] (written) from ``low_grad`` / ``high_grad`` [N, H, w]:
    the gradient of the even and odd extended samples (contiguous runs per tap, as in the forward), then every
    extended sample's gradient added onto the image column it copies (``cols``)."""
    n_planes, height, width = grad_image.shape
    n_taps = taps_lo.shape[0]
    width_out = low_grad.shape[2]
    n_phase = width_out + n_taps // 2 - 1  # as in the forward
    for row in prange(n_planes * height):
        n, t = _plane_row(row, height)
        even = np.zeros(n_phase)
        odd = np.zeros(n_phase)
        for j in range(n_taps):
            phase, offset = _tap_phase(j, even, odd)
            for s in range(width_out):
                phase[s + offset] += taps_lo[j] * low_grad[n, t, s] + taps_hi[j] * high_grad[n, t, s]
        acc = np.zeros(width)
        # the phases cover the extended positions the correlation reads, [0, 2 (w - 1) + L)
        for k in range(n_phase):
            acc[cols[2 * k]] += even[k]
            acc[cols[2 * k + 1]] += odd[k]
        for c in range(width):
            grad_image[n, t, c] = acc[c]


# The moment and L1 sums may be reassociated (vectorized reductions: ~1.7x on the moments here): the order is still
# fixed by the compiled code, so results stay deterministic and independent of the thread count.
_REDUCTION_MATH = {"reassoc"}


@njit(cache=True, fastmath=_REDUCTION_MATH)
def plane_square_sums(x, out):
    """``out[n]`` += sum of x[n]^2 (float64): x [N, K]."""
    for n in range(x.shape[0]):
        total = 0.0
        for k in range(x.shape[1]):
            value = np.float64(x[n, k])
            total += value * value
        out[n] += total


# Pixels per work item of the moment passes: partial sums per (plane, chunk) are combined in chunk order, so the
# result does not depend on how many threads took the chunks.
MOMENT_CHUNK = 2048
# partial-sum slots of band_moments' second pass: m2 (3), m4 (3), cross products (0,1), (0,2), (1,2)
N_MOMENT_SLOTS = 9


@njit(inline="always")
def _chunk_bounds(item, n_chunks, count):
    """(plane, first pixel, end pixel) of work item ``item`` over [N, n_chunks]."""
    n = item // n_chunks
    first = (item - n * n_chunks) * MOMENT_CHUNK
    return n, first, min(first + MOMENT_CHUNK, count)


@njit(parallel=True, cache=True, fastmath=_REDUCTION_MATH)
def band_moments(bands, inv_rms, want_m4, want_cov, means, m2, m4, cross):
    """Moments of the RMS-normalized, centred detail bands of one level: bands [N, 3, P], inv_rms [N] (float64).

    Writes (float64) means [N, 3] (of x), m2 [N, 3] = mean z^2, m4 [N, 3] = mean z^4 (if want_m4) and cross
    [N, 3, 3] = z_a . z_b / max(P - 1, 1) (if want_cov), z = (x - mean) inv_rms. Two passes (the means first), each
    parallel over (plane, chunk of MOMENT_CHUNK pixels).
    """
    n_planes, _, count = bands.shape
    n_chunks = (count + MOMENT_CHUNK - 1) // MOMENT_CHUNK
    partial = np.zeros((n_planes * n_chunks, N_MOMENT_SLOTS))
    for item in prange(n_planes * n_chunks):
        n, first, end = _chunk_bounds(item, n_chunks, count)
        for b in range(N_DETAIL_BANDS):
            total = 0.0
            for k in range(first, end):
                total += np.float64(bands[n, b, k])
            partial[item, b] = total
    for n in range(n_planes):
        for b in range(N_DETAIL_BANDS):
            total = 0.0
            for c in range(n_chunks):
                total += partial[n * n_chunks + c, b]
            means[n, b] = total / count
    for item in prange(n_planes * n_chunks):
        n, first, end = _chunk_bounds(item, n_chunks, count)
        scale = inv_rms[n]
        sums = np.zeros(N_MOMENT_SLOTS)
        for k in range(first, end):
            z0 = (np.float64(bands[n, 0, k]) - means[n, 0]) * scale
            z1 = (np.float64(bands[n, 1, k]) - means[n, 1]) * scale
            z2 = (np.float64(bands[n, 2, k]) - means[n, 2]) * scale
            q0 = z0 * z0
            q1 = z1 * z1
            q2 = z2 * z2
            sums[0] += q0
            sums[1] += q1
            sums[2] += q2
            if want_m4:
                sums[3] += q0 * q0
                sums[4] += q1 * q1
                sums[5] += q2 * q2
            if want_cov:
                sums[6] += z0 * z1
                sums[7] += z0 * z2
                sums[8] += z1 * z2
        for slot in range(N_MOMENT_SLOTS):
            partial[item, slot] = sums[slot]
    norm = max(count - 1, 1)
    for n in range(n_planes):
        sums = np.zeros(N_MOMENT_SLOTS)
        for c in range(n_chunks):
            for slot in range(N_MOMENT_SLOTS):
                sums[slot] += partial[n * n_chunks + c, slot]
        for b in range(N_DETAIL_BANDS):
            m2[n, b] = sums[b] / count
            m4[n, b] = sums[3 + b] / count
        if want_cov:
            for b in range(N_DETAIL_BANDS):
                cross[n, b, b] = sums[b] / norm
            cross[n, 0, 1] = cross[n, 1, 0] = sums[6] / norm
            cross[n, 0, 2] = cross[n, 2, 0] = sums[7] / norm
            cross[n, 1, 2] = cross[n, 2, 1] = sums[8] / norm


@njit(inline="always")
def _moment_adjoint_at(bands, n, k, means, scale, coef2, coef4, sym):
    """dz of the three bands at pixel k of plane n (see :func:`band_moments_adjoint`)."""
    z0 = (np.float64(bands[n, 0, k]) - means[n, 0]) * scale
    z1 = (np.float64(bands[n, 1, k]) - means[n, 1]) * scale
    z2 = (np.float64(bands[n, 2, k]) - means[n, 2]) * scale
    d0 = z0 * (coef2[n, 0] + coef4[n, 0] * z0 * z0) + sym[n, 0, 0] * z0 + sym[n, 0, 1] * z1 + sym[n, 0, 2] * z2
    d1 = z1 * (coef2[n, 1] + coef4[n, 1] * z1 * z1) + sym[n, 1, 0] * z0 + sym[n, 1, 1] * z1 + sym[n, 1, 2] * z2
    d2 = z2 * (coef2[n, 2] + coef4[n, 2] * z2 * z2) + sym[n, 2, 0] * z0 + sym[n, 2, 1] * z1 + sym[n, 2, 2] * z2
    return d0, d1, d2


@njit(parallel=True, cache=True, fastmath=_REDUCTION_MATH)
def band_moments_adjoint(bands, inv_rms, means, coef2, coef4, sym, grad):
    """Adjoint of :func:`band_moments`: ``grad`` [N, 3, P] (written) = dz - mean(dz) with
    dz_a = z_a (coef2_a + coef4_a z_a^2) + sum_b sym_ab z_b; coef2, coef4 [N, 3] and sym [N, 3, 3] (float64) already
    carry the 1/P, 1/(P - 1) and inv_rms factors. Two passes (the mean of dz first, by chunks as in the forward);
    z is recomputed, not stored."""
    n_planes, _, count = bands.shape
    n_chunks = (count + MOMENT_CHUNK - 1) // MOMENT_CHUNK
    partial = np.zeros((n_planes * n_chunks, N_DETAIL_BANDS))
    for item in prange(n_planes * n_chunks):
        n, first, end = _chunk_bounds(item, n_chunks, count)
        scale = inv_rms[n]
        total0 = 0.0
        total1 = 0.0
        total2 = 0.0
        for k in range(first, end):
            d0, d1, d2 = _moment_adjoint_at(bands, n, k, means, scale, coef2, coef4, sym)
            total0 += d0
            total1 += d1
            total2 += d2
        partial[item, 0] = total0
        partial[item, 1] = total1
        partial[item, 2] = total2
    shift = np.zeros((n_planes, N_DETAIL_BANDS))
    for n in range(n_planes):
        for c in range(n_chunks):
            for b in range(N_DETAIL_BANDS):
                shift[n, b] += partial[n * n_chunks + c, b]
        for b in range(N_DETAIL_BANDS):
            shift[n, b] /= count
    for item in prange(n_planes * n_chunks):
        n, first, end = _chunk_bounds(item, n_chunks, count)
        scale = inv_rms[n]
        shift0 = shift[n, 0]
        shift1 = shift[n, 1]
        shift2 = shift[n, 2]
        for k in range(first, end):
            d0, d1, d2 = _moment_adjoint_at(bands, n, k, means, scale, coef2, coef4, sym)
            grad[n, 0, k] = d0 - shift0
            grad[n, 1, k] = d1 - shift1
            grad[n, 2, k] = d2 - shift2


@njit(cache=True, fastmath=_REDUCTION_MATH)
def abs_difference_sum(pred, target):
    """sum |pred - target| (float64) over two flat arrays of one length."""
    total = 0.0
    for k in range(pred.shape[0]):
        total += abs(np.float64(pred[k]) - np.float64(target[k]))
    return total


@njit(cache=True)
def abs_difference_grad(pred, target, scale, grad):
    """grad = scale * sign(pred - target) (0 where equal, as torch's l1_loss), flat arrays."""
    for k in range(pred.shape[0]):
        difference = pred[k] - target[k]
        grad[k] = scale if difference > 0 else (-scale if difference < 0 else 0.0)
