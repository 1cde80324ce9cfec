"""Differentiable 2D discrete wavelet transform (multi-level, orthogonal Daubechies), PyWavelets-compatible.

`dwt2(x [B,C,H,W]) -> WaveletCoeffs(approx [B,C,h,w], details [[B,C,3,h_j,w_j], ...] finest first)`, with the
orientations in PyWavelets' order (cH, cV, cD) = the paper's (LH, HL, HH). The coefficients equal
`pywt.wavedec2(x, wave, mode=mode, level=levels)` (reversed) for the modes symmetric, reflect, zero, periodization.

Implementation: a level is one extension of the image on both axes followed by the four separable 2D filters (lo/hi
along H times lo/hi along W) at stride 2. On CPU (`_SeparableLevel`, the index-map modes) that is two compiled
separable passes that read the extension through index maps, float64 sums, with their adjoints written out
(`_dwt_kernels.py`); elsewhere, and for the zero mode, ONE strided `conv2d` with the 2D bank after `F.pad` or an
index gather (the torch path, also the tests' oracle). Gradients are exact in every mode (float64 gradcheck passes)
and the transform runs on any device. PyWavelets is never imported here: the filter taps come from Daubechies'
spectral factorization (`daubechies_filters`), checked against `pywt.Wavelet` in the tests. docs/losses.md has the
measurements behind these choices.
"""

from __future__ import annotations

import functools
import math
import re
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from kc_splatfacto import backend

# Boundary modes, named as in PyWavelets.
MODES = ("symmetric", "reflect", "zero", "periodization")
# Daubechies orders this module can build (pywt ships db1..db38; spectral factorization in float64 matches its taps
# to ~1e-14 up to db7 and ~1e-12 up to db10, then root finding degrades: larger orders are refused, not inexact).
MAX_DB_ORDER = 10

# Every statistic is computed on the bands divided by the image's RMS coefficient magnitude s (detached; by Parseval
# ~ the RMS pixel): kurtosis and correlation do not depend on scale, and covariance is s^2 cov(c / s) exactly, so
# nothing changes mathematically, but every intermediate is O(1) whatever the intensity scale (x1e4, x1e-6), and the
# backward of rsqrt(m2 + eps) stays far from float32 overflow even for an all-black image.
# eps on a normalized band's variance: 1e-12 = a standard deviation of 1e-6 of the image's RMS, ~10x above float32
# rounding noise of the transform and ~4000x below an 8-bit quantization step. Every real band is untouched (a
# sigma-3 blurred photo's finest diagonal band, std 2e-5 RMS, keeps its kurtosis to 1%), while a constant or
# rounding-noise band (variance ~0) gets kurtosis -3 with a bounded gradient instead of 0/0. docs/losses.md has the
# measured sweep.
VARIANCE_REL_EPS = 1e-12
"""eps on a band's variance relative to the image's mean coefficient power (the statistics of losses.frequency and
the fused path)"""


@dataclass
class WaveletCoeffs:
    """Multi-level 2D DWT of a batch of images.

    approx:  [B, C, h_J, w_J] coarsest approximation (LL) subband.
    details: list of J tensors, finest first; details[j-1] is [B, C, 3, h_j, w_j] holding (cH, cV, cD) of level j.
    approximations: the approximation (LL) band of every level, finest first, [B, C, h_j, w_j] (the last is
             ``approx``; empty when no level was taken).
    """

    approx: Tensor
    details: list[Tensor]
    approximations: list[Tensor] = field(default_factory=list)

    @property
    def levels(self) -> int:
        return len(self.details)

    def without_finest(self, count: int) -> WaveletCoeffs:
        """These coefficients less the ``count`` finest levels' bands (``approx``, the coarsest, stays)."""
        return WaveletCoeffs(self.approx, self.details[count:], self.approximations[count:])

    def detach(self) -> WaveletCoeffs:
        return WaveletCoeffs(self.approx.detach(), [d.detach() for d in self.details],
                             [a.detach() for a in self.approximations])

    def to(self, *args, **kwargs) -> WaveletCoeffs:
        return WaveletCoeffs(self.approx.to(*args, **kwargs), [d.to(*args, **kwargs) for d in self.details],
                             [a.to(*args, **kwargs) for a in self.approximations])


# --------------------------------------------------------------------------------------------------- filters


def _daubechies_order(wave: str) -> int:
    name = wave.lower()
    if name == "haar":
        return 1
    match = re.fullmatch(r"db(\d+)", name)
    if match is None or not 1 <= int(match.group(1)) <= MAX_DB_ORDER:
        raise ValueError(f"unknown wavelet '{wave}': use 'haar' or 'db1' .. 'db{MAX_DB_ORDER}' (orthogonal Daubechies)")
    return int(match.group(1))


@functools.cache
def daubechies_filters(wave: str) -> tuple[np.ndarray, np.ndarray]:
    """Decomposition filters (dec_lo, dec_hi) of an orthogonal Daubechies wavelet, float64, PyWavelets' convention.

    Spectral factorization: the squared magnitude response of the order-N low-pass is
    |H|^2 = cos^{2N}(w/2) * P(sin^2(w/2)),  P(y) = sum_{k<N} binom(N-1+k, k) y^k.
    Substituting y = (2 - z - 1/z) / 4 turns P into a Laurent polynomial whose roots come in pairs (r, 1/r); the
    extremal-phase (minimum-phase) filter keeps the roots inside the unit circle. rec_lo = that filter normalized to
    sum sqrt(2); dec_lo = reversed rec_lo; dec_hi[k] = (-1)^(k+1) rec_lo[k] (the quadrature mirror).
    """
    order = _daubechies_order(wave)
    # P(y) as a polynomial in z (times z^(N-1)): y = (-z^2 + 2z - 1) / (4z).
    poly_z = np.zeros(1)
    y_num = np.array([-1.0, 2.0, -1.0]) / 4.0  # numerator of y in z (highest power first)
    for k in range(order):
        term = np.array([float(math.comb(order - 1 + k, k))])
        for _ in range(k):
            term = np.convolve(term, y_num)
        # multiply by z^(N-1-k) so every term has the common denominator z^(N-1)
        term = np.concatenate([term, np.zeros(order - 1 - k)])
        width = max(len(poly_z), len(term))
        poly_z = np.pad(poly_z, (width - len(poly_z), 0)) + np.pad(term, (width - len(term), 0))
    roots = np.roots(poly_z) if order > 1 else np.zeros(0)
    inside = roots[np.abs(roots) < 1.0]
    rec_lo = np.array([1.0])
    for _ in range(order):
        rec_lo = np.convolve(rec_lo, [1.0, 1.0])
    for root in inside:
        rec_lo = np.convolve(rec_lo, [1.0, -root])
    rec_lo = np.real(rec_lo)
    rec_lo = rec_lo * (math.sqrt(2.0) / rec_lo.sum())
    dec_lo = rec_lo[::-1].copy()
    signs = np.array([(-1.0) ** (k + 1) for k in range(len(rec_lo))])
    dec_hi = signs * rec_lo
    return dec_lo, dec_hi


@functools.cache
def _correlation_taps(wave: str) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) [L] float64: the taps one level correlates with (the decomposition filters reversed: conv2d and the
    CPU kernels correlate)."""
    dec_lo, dec_hi = daubechies_filters(wave)
    return np.ascontiguousarray(dec_lo[::-1]), np.ascontiguousarray(dec_hi[::-1])


@functools.cache
def _filter_bank_np(wave: str) -> np.ndarray:
    """[4, 1, L, L] cross-correlation weights of the four 2D analysis filters, in the order (cA, cH, cV, cD).

    cH is PyWavelets' 'da' (high-pass along H, low-pass along W), cV is 'ad', cD is 'dd'.
    """
    lo, hi = _correlation_taps(wave)
    pairs = ((lo, lo), (hi, lo), (lo, hi), (hi, hi))  # (along H, along W)
    return np.stack([np.outer(fh, fw) for fh, fw in pairs])[:, None]


@functools.cache
def _filter_bank(wave: str, dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.as_tensor(_filter_bank_np(wave), dtype=dtype, device=device)


# --------------------------------------------------------------------------------------------------- levels


def filter_length(wave: str) -> int:
    return 2 * _daubechies_order(wave)


def dwt_max_level(data_len: int, filter_len: int) -> int:
    """PyWavelets' rule: the deepest level at which the filter still fits the signal (0 when it never does)."""
    if data_len < filter_len - 1:
        return 0
    return math.floor(math.log2(data_len / (filter_len - 1)))


def coeff_length(n: int, filter_len: int, mode: str) -> int:
    """Length of one level's coefficients along an axis of length n (PyWavelets' dwt_coeff_len)."""
    if mode == "periodization":
        return (n + 1) // 2
    return (n + filter_len - 1) // 2


# --------------------------------------------------------------------------------------------------- padding

def _extension_index(n: int, filter_len: int, mode: str) -> np.ndarray:
    """Indices into an axis of length n whose gather is the extended axis one stride-2 correlation needs.

    Non-periodized modes: PyWavelets computes c[k] = sum_j f[j] x[2k + 1 - j] over the signal extended on both sides,
    so the window of c[k] starts at x[2k + 2 - L]: pad L - 2 on the left and L - 1 on the right.
    Periodization: an odd axis first repeats its last sample; then c[k] = sum_j f[j] x[(2k + L/2 - j) mod n_even].
    """
    if mode == "periodization":
        n_even = n + (n % 2)
        half = filter_len // 2
        positions = np.arange(half + 1 - filter_len, 2 * ((n_even) // 2 - 1) + half + 1)
        positions = np.mod(positions, n_even)
        return np.minimum(positions, n - 1)  # the duplicated last sample of an odd axis
    positions = np.arange(2 - filter_len, n + filter_len - 1)
    if mode == "symmetric":  # half-sample symmetric: ... x1 x0 | x0 x1 ... x_{n-1} | x_{n-1} x_{n-2} ...
        period = 2 * n
        positions = np.mod(positions, period)
        return np.where(positions >= n, period - 1 - positions, positions)
    if mode == "reflect":  # whole-sample symmetric: ... x2 x1 | x0 x1 ... x_{n-1} | x_{n-2} ...
        if n == 1:
            return np.zeros_like(positions)
        period = 2 * n - 2
        positions = np.mod(positions, period)
        return np.where(positions >= n, period - positions, positions)
    raise ValueError(f"no index map for mode '{mode}'")


@functools.cache
def _index_tensor(n: int, filter_len: int, mode: str, device: torch.device) -> Tensor:
    return torch.as_tensor(_extension_index(n, filter_len, mode), dtype=torch.long, device=device)


def _pad(x: Tensor, filter_len: int, mode: str) -> Tensor:
    """Extend [N, 1, H, W] on both spatial axes so a valid stride-2 correlation yields one DWT level.

    The torch path: every mode on devices other than the CPU, and the zero mode on the CPU (`_SeparableLevel` does
    the other modes there). F.pad where it builds the same extension, two index gathers otherwise. On a GPU the step is bound by kernel
    launches, not passes: the two-gather path (2 launches forward, 2 backward) beat a slice/flip path (~9 forward,
    ~14 backward) for the symmetric mode; measured on an H100 (docs/results/gpu/README.md).
    """
    height, width = x.shape[-2:]
    before, after = filter_len - 2, filter_len - 1
    if mode == "zero":
        return F.pad(x, (before, after, before, after))
    if mode == "reflect" and after < min(height, width):
        return F.pad(x, (before, after, before, after), mode="reflect")
    if mode == "periodization":
        # an odd axis first repeats its last sample (PyWavelets), then wraps around by L/2 - 1 on both sides
        if height % 2:
            x = torch.cat([x, x[..., -1:, :]], dim=-2)
        if width % 2:
            x = torch.cat([x, x[..., -1:]], dim=-1)
        wrap = filter_len // 2 - 1
        if wrap <= min(x.shape[-2:]):
            return F.pad(x, (wrap, wrap, wrap, wrap), mode="circular") if wrap else x
        height, width = x.shape[-2:]  # even now: the index map below sees no odd axis
    rows = _index_tensor(height, filter_len, mode, x.device)
    cols = _index_tensor(width, filter_len, mode, x.device)
    return x.index_select(-2, rows).index_select(-1, cols)


@functools.cache
def _extension_maps(n: int, filter_len: int, mode: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An axis's index map (`_extension_index`) and its inverse over the positions one level reads, as CSR:
    image sample t is read at extended positions ``pos[ptr[t]:ptr[t + 1]]`` (ascending)."""
    index = _extension_index(n, filter_len, mode).astype(np.int64)
    n_out = (index.size - filter_len) // 2 + 1
    used = index[: 2 * (n_out - 1) + filter_len]
    pos = np.argsort(used, kind="stable").astype(np.int64)
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(used, minlength=n), out=ptr[1:])
    return index, ptr, pos


class _SeparableLevel(torch.autograd.Function):
    """One DWT level on CPU: x [N, 1, H, W] -> (cA [N, 1, h, w], (cH, cV, cD) [N, 3, h, w]), extension by index maps.

    Two compiled separable passes (``_dwt_kernels.level_rows`` / ``level_cols``, float64 sums) and their adjoints
    gathered per image row; the same coefficients as the torch path (`_pad` + the bank's conv2d) to float rounding,
    float64 gradcheck passes (tests/losses/test_wavelets.py). The detail bands come out contiguous, so the moment
    pass and the L1 read them without copies.
    """

    @staticmethod
    def forward(ctx, x: Tensor, wave: str, mode: str):
        from kc_splatfacto.losses import _dwt_kernels as kernels

        count, _, height, width = x.shape
        filter_len = filter_length(wave)
        taps_lo, taps_hi = _correlation_taps(wave)
        rows, row_ptr, row_pos = _extension_maps(height, filter_len, mode)
        cols, _, _ = _extension_maps(width, filter_len, mode)
        height_out = (rows.size - filter_len) // 2 + 1
        width_out = (cols.size - filter_len) // 2 + 1
        low = np.empty((count, height, width_out))
        high = np.empty_like(low)
        kernels.level_rows(x.detach().contiguous()[:, 0].numpy(), cols, taps_lo, taps_hi, low, high)
        approx = x.new_empty((count, 1, height_out, width_out))
        detail = x.new_empty((count, kernels.N_DETAIL_BANDS, height_out, width_out))
        kernels.level_cols(low, high, rows, taps_lo, taps_hi, approx.numpy(), detail.numpy())
        ctx.maps = (cols, row_ptr, row_pos, taps_lo, taps_hi)
        ctx.image_shape = (count, 1, height, width)
        return approx, detail

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_approx: Tensor, grad_detail: Tensor):
        from kc_splatfacto.losses import _dwt_kernels as kernels

        cols, row_ptr, row_pos, taps_lo, taps_hi = ctx.maps
        count, _, height, _ = ctx.image_shape
        low_grad = np.empty((count, height, grad_detail.shape[-1]))
        high_grad = np.empty_like(low_grad)
        kernels.level_cols_adjoint(grad_approx.contiguous().numpy(), grad_detail.contiguous().numpy(), row_ptr,
                                   row_pos, taps_lo, taps_hi, low_grad, high_grad)
        grad_x = grad_detail.new_empty(ctx.image_shape)
        kernels.level_rows_adjoint(low_grad, high_grad, cols, taps_lo, taps_hi, grad_x[:, 0].numpy())
        return grad_x, None, None


# modes whose extension is an index map (zero padding is not: it inserts values)
_INDEX_MODES = ("symmetric", "reflect", "periodization")


def _level(x: Tensor, wave: str, filter_len: int, mode: str, bank: Tensor) -> tuple[Tensor, Tensor]:
    """One DWT level of x [N, 1, H, W]: (cA [N, 1, h, w], (cH, cV, cD) [N, 3, h, w])."""
    if backend.compiled(x) and mode in _INDEX_MODES:
        # (periodization's index map repeats the last sample of an odd axis itself, as PyWavelets does)
        return _SeparableLevel.apply(x, wave, mode)
    out = F.conv2d(_pad(x, filter_len, mode), bank, stride=2)
    # split, not two slices: its backward is one cat instead of two zero-filled full-size buffers
    approx, detail = out.split([1, 3], dim=1)
    return approx, detail


# --------------------------------------------------------------------------------------------------- transform


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    if not dtype.is_floating_point:
        raise TypeError(f"dwt2 needs a floating-point image, got {dtype}")
    # Half precision loses the small detail coefficients (and their 4th powers) that the statistics rely on.
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype


def supported_levels(height: int, width: int, wave: str = "db3", levels: int = 3) -> int:
    """How many of `levels` an image of height x width supports (PyWavelets' dwt_max_level on the shorter side)."""
    return min(levels, dwt_max_level(min(height, width), filter_length(wave)))


def dropped_levels_phrase(dropped: int, levels: int) -> str:
    """'the coarsest level is', 'the 2 coarsest levels are', 'all 3 levels are': the subject of a warning's
    "... left out" for ``dropped`` of ``levels`` levels."""
    if dropped >= levels:
        return f"all {levels} levels are" if levels > 1 else "the level is"
    return "the coarsest level is" if dropped == 1 else f"the {dropped} coarsest levels are"


def dwt2(x: Tensor, wave: str = "db3", levels: int = 3, mode: str = "symmetric", *, warn: bool = True) -> WaveletCoeffs:
    """Multi-level 2D DWT of x [B, C, H, W]; equals `pywt.wavedec2(x, wave, mode=mode, level=levels)` reversed.

    Returns WaveletCoeffs(approx [B, C, h, w], details finest first, each [B, C, 3, h_j, w_j] in (cH, cV, cD) order).
    Levels the image cannot support (PyWavelets' `dwt_max_level` rule on min(H, W)) are left out with one warning
    (none with ``warn=False``: a caller that warns once itself, as ``FrequencyLoss`` does); with none left, approx is the image itself. float16/bfloat16 inputs are transformed in float32 (the output is
    float32); other dtypes and any device are kept.
    """
    if x.dim() != 4:
        raise ValueError(f"dwt2 expects x of shape [B, C, H, W], got {tuple(x.shape)}")
    if mode not in MODES:
        raise ValueError(f"unknown mode '{mode}': use one of {MODES}")
    if int(levels) != levels or levels < 0:
        raise ValueError(f"levels must be a non-negative integer, got {levels}")
    flen = filter_length(wave)
    batch, channels, height, width = x.shape
    if height == 0 or width == 0:
        raise ValueError(f"dwt2 got an empty image of size {height}x{width}")
    kept = supported_levels(height, width, wave, levels)
    if kept < levels and warn:
        warnings.warn(
            f"dwt2: a {height}x{width} image supports only {kept} of the {levels} requested {wave} levels "
            f"(filter length {flen}); the remaining {levels - kept} are left out",
            stacklevel=2,
        )
    dtype = _compute_dtype(x.dtype)
    bank = _filter_bank(wave, dtype, x.device)
    current = x.to(dtype).reshape(batch * channels, 1, height, width)
    details, approximations = [], []
    for _ in range(kept):
        current, detail = _level(current, wave, flen, mode, bank)  # [B*C, 1, h, w], [B*C, 3, h, w]
        h, w = detail.shape[-2:]
        details.append(detail.reshape(batch, channels, 3, h, w))
        approximations.append(current.reshape(batch, channels, h, w))
    approx = current.reshape(batch, channels, *current.shape[-2:])
    return WaveletCoeffs(approx=approx, details=details, approximations=approximations)
