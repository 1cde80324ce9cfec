"""numba kernels of one DWT level on CPU tensors: the boundary extension as a gather and its adjoint as a scatter.

A level is `conv2d(extend(x), bank, stride=2)`. Its backward is the adjoint of the strided correlation (computed in
torch as a stride-1 polyphase convolution, see ``wavelets._phase_bank``) followed by the adjoint of the extension:
every extended sample's gradient added onto the image sample it copies (``rows`` / ``cols`` are the index maps of
``wavelets._extension_index``, so any mode and any axis length are covered, including extensions longer than the axis).
Both loops are one pass over the extended image; torch's slices and flips took ~10 small ops per level for the same.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True)
def gather_extension(image, rows, cols, out):
    """out[n, p, q] = image[n, rows[p], cols[q]]: image [N, H, W] -> out [N, len(rows), len(cols)] (written)."""
    for n in range(image.shape[0]):
        for p in range(rows.size):
            r = rows[p]
            for q in range(cols.size):
                out[n, p, q] = image[n, r, cols[q]]


@njit(cache=True)
def scatter_phases(phases, rows, cols, grad):
    """Adjoint of :func:`gather_extension` applied to a polyphase gradient: grad [N, H, W] (zeroed) += for every
    extended position (p, q) the value phases[n, 2 (p % 2) + q % 2, p // 2, q // 2].

    phases [N, 4, h2, w2] holds the gradient of the extended image split by (row parity, column parity); extended
    positions at or past (2 h2, 2 w2) get no gradient (the strided correlation never reads them).
    """
    rows_used = min(rows.size, 2 * phases.shape[2])
    cols_used = min(cols.size, 2 * phases.shape[3])
    for n in range(grad.shape[0]):
        for p in range(rows_used):
            r = rows[p]
            row_phase = 2 * (p & 1)
            i = p >> 1
            for q in range(cols_used):
                grad[n, r, cols[q]] += phases[n, row_phase + (q & 1), i, q >> 1]
