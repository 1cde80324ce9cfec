"""The three frequency terms of :class:`~kc_splatfacto.losses.frequency.FrequencyLoss` as one autograd Function in
few tensor operations: the torch path a GPU runs, where a step is bound by kernel launches, not arithmetic.

The DWT is linear and separable, so every detail band of every level is ``R X C^T`` with ``R`` (along H) and ``C``
(along W) the products of the levels' analysis matrices (the boundary extension included). The K = 3J + 1 bands
(slot ``o * J + (j - 1)`` for orientation o in (H, V, D) and level j, the coarsest approximation last) are computed
together by two batched matrix products into one tensor ``Y [K, h, w, N]`` (N = images x channels, channels last as
the render is laid out), each band in the top-left corner of its slot and exact zeros around it. One pass over ``Y``
then gives every band's mean, second and fourth moment and the cross products of a level's three orientations as
reductions, and the loss formulas run once on the small [3J, N] statistics. The backward is written out (the same
formulas' derivatives, then the transposed matrix products).

The numbers equal the level-by-level path's (:mod:`._frequency_autograd`, itself held to PyWavelets and scipy) to
float rounding. Where the two split the gradient of a maximum differently (ties among the bands' kurtosis: this
path gives it to the first band, autograd's ``amax`` shares it) both are subgradients of the same loss.

Used for the supervised kurtosis and covariance terms (the paper's settings): the frequency loss's table of terms
(``frequency.TERMS``) says which settings each term is computed here for; the others (the unsupervised and
correlation variants, the terms without a kernel here) run level by level beside these.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from kc_splatfacto.losses.wavelets import (
    VARIANCE_REL_EPS,
    _correlation_taps,
    _extension_index,
    filter_length,
    supported_levels,
)

POWER_FLOOR = 1e-30
"""floor of the image power s^2 (as the level-by-level path): only an all-zero image reaches it"""


# --------------------------------------------------------------------------------------------------- the plan


def _level_matrices(n: int, wave: str, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """One DWT level along an axis of length n as (lo [n_out, n], hi [n_out, n]) float64: c[k] = sum_t f[t]
    ext[2k + t] with ext the boundary extension (an index map, or zeros for the zero mode)."""
    length = filter_length(wave)
    taps_lo, taps_hi = _correlation_taps(wave)
    if mode == "zero":
        positions = np.arange(2 - length, n + length - 1)
    else:
        positions = _extension_index(n, length, mode)
    n_out = (positions.size - length) // 2 + 1
    rows = np.repeat(np.arange(n_out), length)
    sources = positions[2 * rows + np.tile(np.arange(length), n_out)]
    inside = (sources >= 0) & (sources < n)  # (always, but for the zero mode's padding)
    lo, hi = np.zeros((n_out, n)), np.zeros((n_out, n))
    np.add.at(lo, (rows[inside], sources[inside]), np.tile(taps_lo, n_out)[inside])
    np.add.at(hi, (rows[inside], sources[inside]), np.tile(taps_hi, n_out)[inside])
    return lo, hi


def _axis_operators(n: int, wave: str, mode: str, levels: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per level j = 1..J the composed operators along one axis: (low-pass of level j applied after the low-passes of
    levels < j, high-pass of level j after them), each [n_j, n]."""
    lows, highs = [], []
    current = np.eye(n)
    for _ in range(levels):
        lo, hi = _level_matrices(current.shape[0], wave, mode)
        highs.append(hi @ current)
        current = lo @ current
        lows.append(current)
    return lows, highs


@dataclass(frozen=True)
class BandPlan:
    """The constants of one image size and DWT: the band operators and the per-slot counts and weights.

    row_ops [K, h, H]: slot k's operator along H; col_ops [W, C w]: the C = 2J distinct operators along W (the
    composed low- and high-passes of each level), side by side and transposed; col_of_slot [K] (long): which of them
    slot k uses; mask [3J, h, 1, w] (1 inside each detail band); inv_count [3J, 1, 1, 1] (1 / the band's pixel count
    P_j); count [3J, 1] (P_j); two_over_count and four_over_count [3J, 1, 1, 1] (2 / P_j, 4 / P_j: the moments'
    derivatives); pair_count [J, 1] (max(P_j - 1, 1): numpy.cov's divisor); plus_minus [2, 1] (+1, -1); total (the
    coefficient count of every band and the approximation, the image power's divisor); sizes [(h_j, w_j)] per level.
    """

    levels: int
    row_ops: Tensor
    col_ops: Tensor
    col_of_slot: Tensor
    mask: Tensor
    inv_count: Tensor
    count: Tensor
    two_over_count: Tensor
    four_over_count: Tensor
    pair_count: Tensor
    plus_minus: Tensor
    total: int
    sizes: tuple[tuple[int, int], ...]

    @property
    def slots(self) -> int:
        return self.row_ops.shape[0]

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w): a slot's size (the finest level's band)."""
        return self.row_ops.shape[1], self.col_ops.shape[1] // (2 * self.levels)


@functools.lru_cache(maxsize=16)
def band_plan(height: int, width: int, wave: str, mode: str, levels: int, dtype: torch.dtype,
              device: torch.device) -> BandPlan:
    """The :class:`BandPlan` of an image size (levels: the kept ones, see ``wavelets.supported_levels``); cached, as
    the resolution schedule uses three sizes a run."""
    lows_h, highs_h = _axis_operators(height, wave, mode, levels)
    lows_w, highs_w = _axis_operators(width, wave, mode, levels)
    distinct_cols = lows_w + highs_w  # column operator c: level c + 1's low-pass, or level c - J + 1's high-pass
    rows, col_of_slot = [], []
    for pick_h, col_offset in ((highs_h, 0), (lows_h, levels), (highs_h, levels)):  # cH ('da'), cV ('ad'), cD
        rows += pick_h
        col_of_slot += [col_offset + j for j in range(levels)]
    rows.append(lows_h[-1])  # the approximation: low-pass along both axes
    col_of_slot.append(levels - 1)
    h, w = max(r.shape[0] for r in rows), max(c.shape[0] for c in distinct_cols)
    row_ops = np.zeros((len(rows), h, height))
    for k, r in enumerate(rows):
        row_ops[k, : r.shape[0]] = r
    col_ops = np.zeros((len(distinct_cols), w, width))
    for c, op in enumerate(distinct_cols):
        col_ops[c, : op.shape[0]] = op
    detail = 3 * levels
    sizes = tuple((highs_h[j].shape[0], lows_w[j].shape[0]) for j in range(levels))
    mask = np.zeros((detail, h, 1, w))
    count = np.zeros(detail)
    for k in range(detail):
        hj, wj = sizes[k % levels]
        mask[k, :hj, :, :wj] = 1.0
        count[k] = hj * wj
    total = int(count.sum()) + lows_h[-1].shape[0] * lows_w[-1].shape[0]

    def as_tensor(array: np.ndarray) -> Tensor:
        return torch.as_tensor(array, dtype=dtype, device=device)

    per_slot = count.reshape(detail, 1, 1, 1)
    return BandPlan(
        levels, as_tensor(row_ops), as_tensor(col_ops.reshape(-1, width).T.copy()),
        torch.as_tensor(col_of_slot, dtype=torch.long, device=device), as_tensor(mask), as_tensor(1.0 / per_slot),
        as_tensor(count).reshape(detail, 1), as_tensor(2.0 / per_slot), as_tensor(4.0 / per_slot),
        as_tensor(np.maximum(count[:levels] - 1.0, 1.0)).reshape(levels, 1), as_tensor(np.array([[1.0], [-1.0]])),
        total, sizes,
    )


def plan_for(image_hw: tuple[int, int], wave: str, mode: str, levels: int, like: Tensor) -> BandPlan | None:
    """The plan of an image [.., H, W] with these settings, or None when the image supports no level."""
    height, width = image_hw
    kept = supported_levels(height, width, wave, levels)
    if kept == 0:
        return None
    return band_plan(height, width, wave, mode, kept, like.dtype, like.device)


# --------------------------------------------------------------------------------------------------- the bands


def as_planes(image: Tensor) -> Tensor:
    """[B, C, H, W] -> [N, H, W], N = B * C (a view when contiguous; a render permuted from [H, W, C] is copied)."""
    batch, channels, height, width = image.shape
    return image.reshape(batch * channels, height, width)


@contextlib.contextmanager
def exact_matmul(device: torch.device) -> Iterator[None]:
    """Full float32 matrix products on CUDA within the block, whatever the caller chose: TF32 (10 mantissa bits) would
    move the bands' fourth moments by ~1e-3 relative, far beyond float32 rounding."""
    if device.type != "cuda" or not torch.backends.cuda.matmul.allow_tf32:
        yield
        return
    torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32 = True


def band_slots(image: Tensor, plan: BandPlan) -> Tensor:
    """Every band of image [N, H, W] in its slot: [K, h, N, w]. Two well-shaped matrix products (one GEMM of all
    the image's rows against the 2J distinct column operators, then one per slot along H), a gather between."""
    planes, height, width = image.shape
    h, w = plan.shape
    with exact_matmul(image.device):
        along_w = torch.mm(image.reshape(planes * height, width), plan.col_ops)  # [N H, C w]
        per_slot = along_w.view(planes, height, -1, w).permute(2, 1, 0, 3).index_select(0, plan.col_of_slot)
        slots = torch.bmm(plan.row_ops, per_slot.view(plan.slots, height, planes * w))
    return slots.view(plan.slots, h, planes, w)


def band_slots_adjoint(grad: Tensor, plan: BandPlan, height: int, width: int) -> Tensor:
    """The transpose of :func:`band_slots` for the detail slots: grad [3J, h, N, w] -> [N, H, W]."""
    detail, h, planes, w = grad.shape
    with exact_matmul(grad.device):
        along_h = torch.bmm(plan.row_ops[:detail].transpose(1, 2), grad.view(detail, h, planes * w))  # [3J, H, N w]
        per_col = grad.new_zeros((planes, height, 2 * plan.levels, w))
        per_col.index_add_(2, plan.col_of_slot[:detail], along_h.view(detail, height, planes, w).permute(2, 1, 0, 3))
        return torch.mm(per_col.view(planes * height, -1), plan.col_ops.t()).view(planes, height, width)


# --------------------------------------------------------------------------------------------------- statistics


@dataclass
class SlotStatistics:
    """One image batch's band statistics in slot order ([3J, ...] orientation-major, N planes last).

    y: the bands [K, h, N, w]; z: the detail bands centred and divided by the image's RMS coefficient s
    [3J, h, N, w]; z2 = z^2; power s^2 and inv_rms 1/s [N, 1]; m2, m4 [3J, N] (normalised central moments);
    q = m4 / (m2 + eps)^2 [3J, N]; kurtosis vector [1 + 3J, N] (spread first, then k); cross [3, J, N]: sums over the
    band of z_o z_(o-1) (the orientation before, cyclically: H.D, V.H, D.V); z_prev: z rolled that way;
    l_cov [N].
    """

    y: Tensor
    z: Tensor
    z2: Tensor
    power: Tensor
    inv_rms: Tensor
    m2: Tensor | None = None
    m4: Tensor | None = None
    shifted: Tensor | None = None
    q: Tensor | None = None
    kurtosis: Tensor | None = None
    extreme: Tensor | None = None
    cross: Tensor | None = None
    z_prev: Tensor | None = None
    cross_norm: Tensor | None = None
    l_cov: Tensor | None = None


def slot_statistics(image: Tensor, plan: BandPlan, kurtosis: bool, covariance: bool) -> SlotStatistics:
    """The statistics of image [N, H, W] the terms need (see :class:`SlotStatistics`); no autograd."""
    detail = 3 * plan.levels
    y = band_slots(image, plan)
    norm = torch.linalg.vector_norm(y, dim=(0, 1, 3)).unsqueeze(-1)  # [N, 1]: the root sum of squares of all bands
    power = norm.square().div_(plan.total).clamp_min_(POWER_FLOOR)
    inv_rms = power.rsqrt()
    details = y[:detail]
    mean = details.sum(dim=(1, 3), keepdim=True).mul_(plan.inv_count)
    z = torch.addcmul(details, mean, plan.mask, value=-1.0).mul_(inv_rms)  # (x - mean) / s inside, 0 around
    z2 = z.square()
    stats = SlotStatistics(y, z, z2, power, inv_rms)
    if kurtosis:
        counts = plan.count
        stats.m2 = z2.sum(dim=(1, 3)).div_(counts)
        stats.m4 = (z2 * z2).sum(dim=(1, 3)).div_(counts)
        stats.shifted = stats.m2 + VARIANCE_REL_EPS
        stats.q = stats.m4 / stats.shifted.square()
        k = stats.q - 3.0
        high, high_at = k.max(dim=0)
        low, low_at = k.min(dim=0)
        stats.kurtosis = torch.cat([(high - low)[None], k])
        stats.extreme = torch.stack([high_at, low_at])  # [2, N]: the bands the spread's gradient goes to
    if covariance:
        z3 = z.view(3, plan.levels, *z.shape[1:])
        stats.z_prev = z3.roll(1, dims=0)
        cross = (z3 * stats.z_prev).sum(dim=(2, 4))  # [3, J, N]
        # L_cov = sum_j ||Sigma^j - diag||_F^2 = 2 s^4 sum_(pairs) (cross / (P_j - 1))^2
        stats.cross = cross.div_(plan.pair_count)
        stats.cross_norm = torch.linalg.vector_norm(stats.cross, dim=(0, 1))
        stats.l_cov = (stats.cross_norm * stats.power.squeeze(-1)).square_().mul_(2.0)
    return stats


# --------------------------------------------------------------------------------------------------- the target


@dataclass
class SlotTarget:
    """The ground truth's side of the fused terms: its detail bands times the L1 weights [3J, h, w, N], its kurtosis
    vector (spread first) [1 + 3J, N] and L_cov [N]."""

    weighted_bands: Tensor | None
    kurtosis: Tensor | None
    l_cov: Tensor | None


def slot_target(details: list[Tensor], kurtosis: Tensor | None, spread: Tensor | None, l_cov: Tensor | None,
                plan: BandPlan, l1_weights: Tensor | None) -> SlotTarget:
    """The target in slot order from the level-by-level target's coefficients and statistics (``details`` [B, C, 3,
    h_j, w_j] finest first, kurtosis [B, C, 3J] level-major, spread and l_cov [B, C])."""
    levels = plan.levels
    planes = details[0].shape[0] * details[0].shape[1]
    weighted = None
    if l1_weights is not None:
        h, w = plan.shape
        slots = details[0].new_zeros((3, levels, h, planes, w))
        for j, band in enumerate(details):
            hj, wj = band.shape[-2:]
            slots[:, j, :hj, :, :wj] = band.permute(2, 3, 0, 1, 4).reshape(3, hj, planes, wj)
        weighted = slots.view(3 * levels, h, planes, w) * l1_weights
    vector = None
    if kurtosis is not None and spread is not None:
        k = kurtosis.reshape(planes, levels, 3).permute(2, 1, 0).reshape(3 * levels, planes)
        vector = torch.cat([spread.reshape(1, planes), k])
    return SlotTarget(weighted, vector, None if l_cov is None else l_cov.reshape(planes))


def slot_target_of_image(image: Tensor, plan: BandPlan, l1_weights: Tensor | None) -> SlotTarget:
    """The target of a ground-truth image [N, H, W] by the render's own operations (equal images: exactly zero)."""
    with torch.no_grad():
        stats = slot_statistics(image, plan, kurtosis=True, covariance=True)
        weighted = None if l1_weights is None else stats.y[: 3 * plan.levels] * l1_weights
        return SlotTarget(weighted, stats.kurtosis, stats.l_cov)


# --------------------------------------------------------------------------------------------------- the terms


def _present(value: Tensor | None) -> Tensor:
    if value is None:  # a caller bug: the statistics a term needs are computed whenever its weight is non-zero
        raise RuntimeError("a statistic the fused frequency terms need was not computed")
    return value


OUTPUTS = ("wavelet_loss", "kc_loss", "cbc_loss")
"""the terms :class:`FusedFrequencyTerms` returns, in order, by their names in ``frequency.TERMS``: a term of the table
marked fused must be one of them"""


class FusedFrequencyTerms(torch.autograd.Function):
    """(wavelet L1, KC, CBC) of image [N, H, W], each times its weight (0 where its weight is 0), against a
    :class:`SlotTarget`: the supervised terms of ``frequency.py``'s formulas, mean over the N planes."""

    @staticmethod
    def forward(ctx, image: Tensor, plan: BandPlan, target: SlotTarget, l1_weights: Tensor | None,
                kc_weight: float, cbc_weight: float):
        planes = image.shape[0]
        stats = slot_statistics(image, plan, kurtosis=kc_weight > 0, covariance=cbc_weight > 0)
        wavelet = kc = cbc = None
        weighted = None
        if l1_weights is not None:
            weighted = stats.y[: 3 * plan.levels] * l1_weights
            wavelet = torch.dist(weighted, _present(target.weighted_bands), p=1)
        if kc_weight > 0:
            kc = torch.dist(_present(stats.kurtosis), _present(target.kurtosis), p=1).mul_(kc_weight / planes)
        if cbc_weight > 0:
            cbc = torch.dist(_present(stats.l_cov), _present(target.l_cov), p=1).mul_(cbc_weight / planes)
        ctx.plan, ctx.target, ctx.stats, ctx.weighted, ctx.l1_weights = plan, target, stats, weighted, l1_weights
        ctx.weights = (kc_weight / planes, cbc_weight / planes)
        ctx.image_hw = image.shape[1:]
        # an inactive term's output: a zero of its own (an autograd Function's outputs must be distinct tensors)
        return tuple(image.new_zeros(()) if term is None else term for term in (wavelet, kc, cbc))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_wavelet: Tensor, grad_kc: Tensor, grad_cbc: Tensor):
        plan, target, stats = ctx.plan, ctx.target, ctx.stats
        kc_scale, cbc_scale = ctx.weights
        grad_z = None
        if stats.kurtosis is not None:
            # d|v - v_gt|_1 = sign(v - v_gt); v = (spread, k); spread = k[max] - k[min]
            grad_vector = torch.sign(stats.kurtosis - target.kurtosis).mul_(grad_kc * kc_scale)
            grad_k = grad_vector[1:]
            grad_k.scatter_add_(0, stats.extreme, grad_vector[:1] * plan.plus_minus)
            # k = m4 / (m2 + eps)^2 - 3: dm4 = dk / (m2 + eps)^2, dm2 = -2 dk q / (m2 + eps)
            grad_m4 = grad_k / stats.shifted.square()
            grad_m2 = (grad_k * stats.q).div_(stats.shifted).mul_(-2.0)
            # m_p = mean z^p over the band: dz = z (2 dm2 + 4 dm4 z^2) / P
            grad_z = torch.addcmul(grad_m2[:, None, :, None] * plan.two_over_count, stats.z2,
                                   grad_m4[:, None, :, None] * plan.four_over_count).mul_(stats.z)
        if stats.l_cov is not None:
            # L = 2 s^4 sum c^2 with c_o = sum z_o z_(o-1) / (P - 1): dz_o = 4 s^4 g (c_o z_(o-1) + c_(o+1) z_(o+1))
            sign = torch.sign(stats.l_cov - target.l_cov).mul_(grad_cbc * cbc_scale)
            coefficient = stats.power.squeeze(-1).square().mul_(sign).mul_(4.0)  # [N]
            per_pair = (stats.cross * coefficient).div_(plan.pair_count)
            z3 = stats.z.view(3, plan.levels, *stats.z.shape[1:])
            grad_cov = stats.z_prev * per_pair[:, :, None, :, None]
            grad_cov.addcmul_(z3.roll(-1, dims=0), per_pair.roll(-1, dims=0)[:, :, None, :, None])
            grad_cov = grad_cov.view_as(stats.z)
            grad_z = grad_cov if grad_z is None else grad_z.add_(grad_cov)
        grad_y = None
        if grad_z is not None:
            # z = (y - mean(y)) / s inside the band (s detached): dy = (dz - mean(dz)) / s inside, 0 around
            mean = grad_z.sum(dim=(1, 3), keepdim=True).mul_(plan.inv_count)
            grad_y = torch.addcmul(grad_z, mean, plan.mask, value=-1.0).mul_(stats.inv_rms)
        if ctx.weighted is not None:
            # d sum w |y - g| = w sign(y - g) (0 where equal, as torch's l1_loss)
            sign = torch.sign(ctx.weighted - target.weighted_bands)
            scale = ctx.l1_weights * grad_wavelet
            grad_y = sign.mul_(scale) if grad_y is None else grad_y.addcmul_(sign, scale)
        if grad_y is None:
            return None, None, None, None, None, None
        height, width = ctx.image_hw
        return band_slots_adjoint(grad_y, plan, height, width), None, None, None, None, None


def l1_slot_weights(plan: BandPlan, level_weights: list[float], wavelet_weight: float, planes: int) -> Tensor:
    """[3J, 1, 1, 1]: wavelet_weight w_j / (N P_j) per slot, so sum_slots |weight y - weight g| is the weighted mean
    L1 of ``frequency.wavelet_l1`` (its 3 w_j times the mean over a level's 3 N P_j coefficients)."""
    per_level = np.tile(np.asarray(level_weights, dtype=np.float64), 3) * (wavelet_weight / planes)
    return torch.as_tensor(per_level, dtype=plan.mask.dtype, device=plan.mask.device).reshape(-1, 1, 1, 1) * plan.inv_count
