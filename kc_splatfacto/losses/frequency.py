"""Frequency-domain losses of KC-3DGS on the detail subbands of a J-level DWT (kornia style: functions + thin module).

Notation: c^j_o is the detail subband of level j (1 = finest) and orientation o in (H, V, D); b runs over the 3J
detail subbands in the order (level 1: H, V, D), (level 2: H, V, D), ...; every statistic is per image and channel.

- wavelet_l1      = sum_j w_j sum_o mean|c^j_o(pred) - c^j_o(gt)|,  w_j = 2^j ("paper"), 2^(J-j+1) ("fine"), 1 ("uniform")
- band_kurtosis   k_b = m4_b / (m2_b + eps s^2)^2 - 3, m_k the central moments of subband b (scipy's biased Fisher
                  kurtosis), s^2 the image's mean coefficient power (detached), eps = 1e-12
- kurtosis_spread = max_b k_b - min_b k_b
- kc_loss         = |spread(pred) - spread(gt)| + sum_b |k_b(pred) - k_b(gt)|        (unsupervised: spread(pred))
- covariance      Sigma^j = Z Z^T / (P - 1), Z the centred, flattened [3, P] stack of (H, V, D) of level j
                  (correlation option: Sigma_uv / sqrt((Sigma_uu + eps s^2)(Sigma_vv + eps s^2)))
- L_cov           = sum_j ||Sigma^j - diag(Sigma^j)||_F^2
- cbc_loss        = |L_cov(pred) - L_cov(gt)|                                         (unsupervised: L_cov(pred))
The kc and cbc terms are averaged over images and channels. An image too small for any level has no detail band:
every term is then 0 (still attached to pred's graph, with a zero gradient). `docs/losses.md` explains the choices
(weighting, padding, eps).

API (kornia's shape: functions that do the work, a thin module that calls them): `wavelet_bands(image)` computes an
image's DWT and statistics once (`WaveletBands`); `wavelet_l1`, `kc_loss` and `cbc_loss` take the bands of pred and
gt, so the three terms share one DWT of the render and KC and CBC one moment pass. The ground truth never needs
gradients: `prepare_target(gt)` is its bands, detached, which a trainer caches per image. `FrequencyLoss(pred,
target)` is `wavelet_bands(pred)` followed by the three functions, each times its weight.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from kc_splatfacto import backend
from kc_splatfacto.losses.wavelets import MODES, WaveletCoeffs, dwt2, supported_levels

WEIGHTINGS = ("paper", "fine", "uniform")
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
# Floor of the image power s^2, only active for an all-zero image (then every band is 0 and s only has to be > 0).
POWER_FLOOR = 1e-30


@dataclass
class FrequencyLossConfig:
    """Settings of :class:`FrequencyLoss`; the defaults are the paper's (Method section; supplementary hyperparameter
    table): wavelet 1e-3 with 2^j level weights, KC 1e-5 and CBC 1e-2 both supervised, db3, 3 levels.
    ``SplatfactoModelConfig`` holds the same fields (same names) and builds this from them."""

    wavelet_weight: float = 1e-3
    """weight of the wavelet L1 on the detail subbands"""
    kc_weight: float = 1e-5
    """weight of the kurtosis-concentration loss"""
    cbc_weight: float = 1e-2
    """weight of the cross-band covariance loss"""
    wave: str = "db3"
    """orthogonal Daubechies wavelet of the DWT"""
    wavelet_levels: int = 3
    """DWT levels (fewer where the image is too small for them, with a warning)"""
    wavelet_mode: str = "symmetric"
    """DWT boundary extension (pywt's names)"""
    wavelet_weighting: str = "paper"
    """per-level weights of the wavelet L1: 'paper' 2^j (j=1 finest), 'fine' 2^(J-j+1), 'uniform' 1"""
    kc_supervised: bool = True
    """KC compares the render's band kurtosis with the GT's (False: the render's spread alone)"""
    cbc_supervised: bool = True
    """CBC compares the render's cross-band covariance with the GT's (False: the render's alone)"""
    cbc_correlation: bool = False
    """CBC on band correlations instead of covariances"""

    @classmethod
    def from_fields(cls, holder: object) -> FrequencyLossConfig:
        """These settings read from the attributes of the same names on ``holder`` (a model config, a loss module):
        the field list is this dataclass's, written once."""
        return cls(**{field.name: getattr(holder, field.name) for field in dataclasses.fields(cls)})

    @property
    def active(self) -> bool:
        """Whether any term has a non-zero weight (with all three at zero the loss is off: Splatfacto)."""
        return self.wavelet_weight > 0 or self.kc_weight > 0 or self.cbc_weight > 0

    def setup(self) -> FrequencyLoss:
        """The loss module these settings describe (validated: bad names and weights raise ValueError)."""
        return FrequencyLoss(**dataclasses.asdict(self))


_PAPER = FrequencyLossConfig()


def _check_finite(x: Tensor, name: str) -> None:
    # one reduction pass: a NaN/Inf anywhere makes the sum non-finite (only then is the exact check needed); the sum
    # is float32 at least, so a large half-precision image does not overflow into the slow path
    total = x.sum(dtype=torch.float32) if x.dtype in (torch.float16, torch.bfloat16) else x.sum()
    if not bool(torch.isfinite(total)) and not bool(torch.isfinite(x).all()):
        raise ValueError(
            f"'{name}' contains NaN or Inf values; the frequency losses need finite images "
            f"(check the renderer output / the loaded image for '{name}')"
        )


def _check_image(x: Tensor, name: str, finite: bool = True) -> None:
    if not isinstance(x, Tensor) or x.dim() != 4:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"'{name}' must be an image batch of shape [B, C, H, W], got {shape}")
    if finite:  # a host synchronisation on CUDA: a caller that checks the whole step itself passes False
        _check_finite(x, name)


def level_weights(levels: int, weighting: str = "paper") -> list[float]:
    """Per-level weights w_1..w_J (level 1 = finest) of the wavelet L1 term."""
    if weighting == "paper":  # the paper's equation: 2^j, so the coarsest level weighs most
        return [2.0**j for j in range(1, levels + 1)]
    if weighting == "fine":  # the paper's text ("finer scales weighted more heavily"): 2^(J-j+1)
        return [2.0 ** (levels - j + 1) for j in range(1, levels + 1)]
    if weighting == "uniform":
        return [1.0] * levels
    raise ValueError(f"unknown weighting '{weighting}': use one of {WEIGHTINGS}")


# --------------------------------------------------------------------------------------------------- statistics


def _image_power(coeffs: WaveletCoeffs) -> Tensor:
    """[B, C, 1] mean square over all the image's coefficients (approx and details), detached, floored."""
    with torch.no_grad():
        total = coeffs.approx.square().sum(dim=(-2, -1))
        count = coeffs.approx.shape[-2] * coeffs.approx.shape[-1]
        for band in coeffs.details:
            total = total + torch.linalg.vector_norm(band, dim=(-3, -2, -1)).square()
            count += band.shape[-3] * band.shape[-2] * band.shape[-1]
        return (total / count).clamp_min(POWER_FLOOR).unsqueeze(-1)


def _image_power_cpu(coeffs: WaveletCoeffs) -> Tensor:
    """:func:`_image_power` in float64 from one compiled pass per band tensor (CPU tensors): [B, C, 1]."""
    from kc_splatfacto.losses._dwt_kernels import plane_square_sums

    batch, channels = coeffs.approx.shape[:2]
    planes = batch * channels
    totals = np.zeros(planes)
    count = 0
    for band in (coeffs.approx, *coeffs.details):
        flat = band.detach().reshape(planes, -1)
        plane_square_sums(flat.contiguous().numpy(), totals)
        count += flat.shape[1]
    power = torch.from_numpy(totals / count).clamp_min(POWER_FLOOR)
    return power.reshape(batch, channels, 1)


class _CentredMoments(torch.autograd.Function):
    """Moments of centred, RMS-normalized subbands z = (x - mean(x)) / s of one level, with an analytic backward.

    x [..., 3, P] -> m2 [..., 3] = mean z^2, m4 [..., 3] = mean z^4 (if wanted), cov [..., 3, 3] = z z^T / (P - 1)
    (if wanted). Backward: dz = z (2 g2 + 4 g4 z^2) / P + (G + G^T) z / (P - 1), then dx = (dz - mean(dz)) / s; s is a
    detached constant. On CPU each direction is one compiled call (``_dwt_kernels.band_moments`` and its adjoint,
    parallel over pixel chunks, float64 sums; inv_rms comes in float64); elsewhere ~5 torch passes over the band where
    autograd through the elementwise chain takes ~12.
    """

    @staticmethod
    def forward(ctx, flat: Tensor, inv_rms: Tensor, want_m4: bool, want_cov: bool):
        if backend.compiled(flat):
            return _CentredMoments._forward_cpu(ctx, flat, inv_rms, want_m4, want_cov)
        count = flat.shape[-1]
        z = torch.addcmul(-flat.mean(dim=-1, keepdim=True) * inv_rms, flat, inv_rms)  # (x - mean) / s, fused
        m2 = torch.linalg.vecdot(z, z) / count
        m4 = cov = z2 = None
        if want_m4:
            z2 = z.square()  # kept for the backward: saves two passes there
            m4 = torch.linalg.vecdot(z2, z2) / count
        if want_cov:
            cov = torch.matmul(z, z.transpose(-1, -2)) / max(count - 1, 1)  # numpy.cov's (P - 1) normalization
        ctx.save_for_backward(z, z2, inv_rms)
        return m2, m4, cov

    @staticmethod
    def _forward_cpu(ctx, flat: Tensor, inv_rms: Tensor, want_m4: bool, want_cov: bool):
        from kc_splatfacto.losses._dwt_kernels import N_DETAIL_BANDS, band_moments

        lead = flat.shape[:-2]
        bands = flat.detach().reshape(-1, N_DETAIL_BANDS, flat.shape[-1]).contiguous()
        planes = bands.shape[0]
        means, m2, m4 = (np.zeros((planes, N_DETAIL_BANDS)) for _ in range(3))
        cross = np.zeros((planes, N_DETAIL_BANDS, N_DETAIL_BANDS))
        scale = inv_rms.detach().to(torch.float64).reshape(planes).contiguous().numpy()
        band_moments(bands.numpy(), scale, want_m4, want_cov, means, m2, m4, cross)
        ctx.save_for_backward(bands)
        ctx.cpu = (means, scale, flat.shape)

        def as_output(moment: np.ndarray) -> Tensor:
            return torch.from_numpy(moment).to(flat.dtype).reshape(*lead, *moment.shape[1:])

        return as_output(m2), as_output(m4) if want_m4 else None, as_output(cross) if want_cov else None

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_m2, grad_m4, grad_cov):
        if hasattr(ctx, "cpu"):
            return _CentredMoments._backward_cpu(ctx, grad_m2, grad_m4, grad_cov), None, None, None
        z, z2, inv_rms = ctx.saved_tensors
        count = z.shape[-1]
        # the 1/s of dx = (dz - mean(dz)) / s is folded into the small coefficients, not applied to the band
        scale = inv_rms.squeeze(-1)  # [..., 1]
        coef2 = ((2.0 / count) * grad_m2 * scale).unsqueeze(-1) if grad_m2 is not None else None
        if grad_m4 is not None:
            coef4 = ((4.0 / count) * grad_m4 * scale).unsqueeze(-1)
            grad = torch.addcmul(coef2, z2, coef4) if coef2 is not None else z2 * coef4
            grad.mul_(z)
        elif coef2 is not None:
            grad = z * coef2
        else:
            grad = torch.zeros_like(z)
        if grad_cov is not None:
            sym = (grad_cov + grad_cov.transpose(-1, -2)) * (inv_rms / max(count - 1, 1))
            matrix = z.shape[-2:]
            grad.view(-1, *matrix).baddbmm_(sym.reshape(-1, 3, 3), z.reshape(-1, *matrix))
        grad.sub_(grad.mean(dim=-1, keepdim=True))
        return grad, None, None, None

    @staticmethod
    def _backward_cpu(ctx, grad_m2: Tensor | None, grad_m4: Tensor | None, grad_cov: Tensor | None) -> Tensor:
        from kc_splatfacto.losses._dwt_kernels import N_DETAIL_BANDS, band_moments_adjoint

        (bands,) = ctx.saved_tensors
        means, scale, flat_shape = ctx.cpu
        planes, _, count = bands.shape
        column = torch.from_numpy(scale).unsqueeze(-1)  # [N, 1] float64

        def coefficients(grad: Tensor | None, factor: float) -> np.ndarray:
            if grad is None:
                return np.zeros((planes, N_DETAIL_BANDS))
            return (grad.to(torch.float64).reshape(planes, N_DETAIL_BANDS) * column * factor).numpy()

        if grad_cov is None:
            sym = np.zeros((planes, N_DETAIL_BANDS, N_DETAIL_BANDS))
        else:
            matrix = grad_cov.to(torch.float64).reshape(planes, N_DETAIL_BANDS, N_DETAIL_BANDS)
            sym = ((matrix + matrix.transpose(-1, -2)) * (column.unsqueeze(-1) / max(count - 1, 1))).numpy()
        grad = torch.empty_like(bands)
        band_moments_adjoint(bands.numpy(), scale, means, coefficients(grad_m2, 2.0 / count),
                             coefficients(grad_m4, 4.0 / count), np.ascontiguousarray(sym), grad.numpy())
        return grad.reshape(flat_shape)


def _level_moments(coeffs: WaveletCoeffs, want_m4: bool, want_cov: bool) -> tuple[list[tuple], Tensor]:
    """Per level (m2 [B, C, 3], m4 or None, cov [B, C, 3, 3] or None) of the RMS-normalized centred subbands,
    and the image power s^2 [B, C, 1] they are normalized by."""
    if backend.compiled(coeffs.approx):
        power64 = _image_power_cpu(coeffs)
        power = power64.to(coeffs.approx.dtype)
        inv_rms = torch.rsqrt(power64).unsqueeze(-1)  # [B, C, 1, 1] float64: the compiled pass's scale
    else:
        power = _image_power(coeffs)
        inv_rms = torch.rsqrt(power).unsqueeze(-1)  # [B, C, 1, 1]
    moments = [_CentredMoments.apply(band.flatten(-2), inv_rms, want_m4, want_cov) for band in coeffs.details]
    return moments, power


def _kurtosis_from_moments(moments: list[tuple], like: Tensor) -> Tensor:
    # the moments are O(1) (normalized by the image RMS), so m4 neither overflows nor underflows where it matters
    kurtosis = [m4 / (m2 + VARIANCE_REL_EPS).square() - 3.0 for m2, m4, _ in moments]
    if not kurtosis:
        return like.new_zeros((*like.shape[:2], 0))
    return torch.cat(kurtosis, dim=-1)


def band_kurtosis(coeffs: WaveletCoeffs) -> Tensor:
    """Excess (Fisher, biased) kurtosis of every detail subband: [B, C, 3J], bands ordered level-major (H, V, D).

    k_b = m4_b / (m2_b + eps s^2)^2 - 3 with central moments m_k and s^2 the image's mean coefficient power; equals
    `scipy.stats.kurtosis(band, fisher=True, bias=True)` up to the relative eps (a constant band gives -3, not NaN).
    """
    return _kurtosis_from_moments(_level_moments(coeffs, True, False)[0], coeffs.approx)


def kurtosis_spread(kurtosis: Tensor) -> Tensor:
    """max_b k_b - min_b k_b over the last axis: [..., 3J] -> [...] (0 when there are no bands)."""
    if kurtosis.shape[-1] == 0:
        return kurtosis.sum(dim=-1)
    return kurtosis.amax(dim=-1) - kurtosis.amin(dim=-1)


def _covariances_from_moments(moments: list[tuple], power: Tensor, correlation: bool) -> list[Tensor]:
    covariances = []
    for _, _, cov in moments:
        if correlation:
            inv_std = torch.rsqrt(torch.diagonal(cov, dim1=-2, dim2=-1) + VARIANCE_REL_EPS)
            cov = cov * inv_std.unsqueeze(-1) * inv_std.unsqueeze(-2)
        else:
            cov = cov * power.unsqueeze(-1)  # undo the normalization: cov(c) = s^2 cov(c / s)
        covariances.append(cov)
    return covariances


def cross_band_covariance(coeffs: WaveletCoeffs, correlation: bool = False) -> list[Tensor]:
    """Per level (finest first), the 3x3 covariance (or correlation) of the centred (H, V, D) subbands: [B, C, 3, 3].

    Equals `numpy.cov(np.stack([cH, cV, cD]).reshape(3, -1))` (correlation: `numpy.corrcoef`, up to eps).
    """
    return _covariances_from_moments(*_level_moments(coeffs, False, True), correlation)


def _off_diagonal_energy(covariances: list[Tensor], like: Tensor) -> Tensor:
    total = like.new_zeros(like.shape[:2])
    for cov in covariances:
        off_diagonal = cov - torch.diag_embed(torch.diagonal(cov, dim1=-2, dim2=-1))
        total = total + off_diagonal.square().sum(dim=(-2, -1))
    return total


def covariance_penalty(coeffs: WaveletCoeffs, correlation: bool = False) -> Tensor:
    """L_cov = sum over levels of the squared off-diagonal Frobenius norm of the cross-band covariance: [B, C]."""
    return _off_diagonal_energy(cross_band_covariance(coeffs, correlation), coeffs.approx)


# --------------------------------------------------------------------------------------------------- bands


@dataclass
class WaveletBands:
    """An image batch's DWT and the statistics the losses compare: what :func:`wavelet_l1`, :func:`kc_loss` and
    :func:`cbc_loss` take for both sides (one DWT of the render shared by the three terms, one moment pass shared by
    KC and CBC).

    coeffs: WaveletCoeffs; kurtosis [B, C, 3J] and spread [B, C] (None unless computed); l_cov [B, C] (None unless
    computed; with ``cbc_correlation``); wave / wavelet_levels (requested) / wavelet_mode / cbc_correlation: the
    settings they were computed with; image_shape: the image's [B, C, H, W].
    """

    coeffs: WaveletCoeffs
    kurtosis: Tensor | None
    spread: Tensor | None
    l_cov: Tensor | None
    wave: str
    wavelet_levels: int
    wavelet_mode: str
    cbc_correlation: bool
    image_shape: tuple[int, ...]

    def to(self, *args, **kwargs) -> WaveletBands:
        def move(x: Tensor | None) -> Tensor | None:
            return None if x is None else x.to(*args, **kwargs)

        return dataclasses.replace(self, coeffs=self.coeffs.to(*args, **kwargs), kurtosis=move(self.kurtosis),
                                   spread=move(self.spread), l_cov=move(self.l_cov))

    @property
    def device(self) -> torch.device:
        return self.coeffs.approx.device

    @property
    def dtype(self) -> torch.dtype:
        return self.coeffs.approx.dtype


def wavelet_bands(
    image: Tensor,
    wave: str = _PAPER.wave,
    wavelet_levels: int = _PAPER.wavelet_levels,
    wavelet_mode: str = _PAPER.wavelet_mode,
    cbc_correlation: bool = _PAPER.cbc_correlation,
    kurtosis: bool = True,
    covariance: bool = True,
    warn_dropped_levels: bool = True,
    check_finite: bool = True,
) -> WaveletBands:
    """The DWT of image [B, C, H, W] and, when asked, its band kurtosis and L_cov (differentiable; raises
    ValueError on NaN/Inf unless ``check_finite`` is False); the statistics not asked for stay None. Levels the image
    is too small for are left out (with :func:`dwt2`'s warning unless ``warn_dropped_levels`` is False)."""
    _check_image(image, "image", finite=check_finite)
    coeffs = dwt2(image, wave=wave, levels=wavelet_levels, mode=wavelet_mode, warn=warn_dropped_levels)
    k = spread = l_cov = None
    if kurtosis or covariance:  # (no level: empty kurtosis [B, C, 0], zero spread and L_cov)
        moments, power = _level_moments(coeffs, kurtosis, covariance)
        if kurtosis:
            k = _kurtosis_from_moments(moments, coeffs.approx)
            spread = kurtosis_spread(k)
        if covariance:
            l_cov = _off_diagonal_energy(_covariances_from_moments(moments, power, cbc_correlation), coeffs.approx)
    return WaveletBands(coeffs, k, spread, l_cov, wave, wavelet_levels, wavelet_mode, cbc_correlation,
                        tuple(image.shape))


def prepare_target(
    gt: Tensor,
    wave: str = _PAPER.wave,
    wavelet_levels: int = _PAPER.wavelet_levels,
    wavelet_mode: str = _PAPER.wavelet_mode,
    cbc_correlation: bool = _PAPER.cbc_correlation,
    warn_dropped_levels: bool = True,
) -> WaveletBands:
    """The ground truth's WaveletBands with every statistic, detached: compute once per image, reuse every step
    (raises ValueError on NaN/Inf naming 'gt')."""
    _check_image(gt, "gt")
    with torch.no_grad():
        return wavelet_bands(gt.detach(), wave, wavelet_levels, wavelet_mode, cbc_correlation,
                             warn_dropped_levels=warn_dropped_levels)


def _check_pair(pred: WaveletBands, gt: WaveletBands, with_correlation: bool = False) -> WaveletBands:
    """gt on pred's device and dtype, after checking that both were computed the same way."""
    for name, x in (("pred", pred), ("gt", gt)):
        if not isinstance(x, WaveletBands):
            raise TypeError(f"'{name}' must be WaveletBands (wavelet_bands(image) / prepare_target(gt)), "
                            f"got {type(x).__name__}")
    settings = ("wave", "wavelet_levels", "wavelet_mode") + (("cbc_correlation",) if with_correlation else ())
    if any(getattr(pred, k) != getattr(gt, k) for k in settings):
        describe = lambda x: ", ".join(f"{k}={getattr(x, k)}" for k in settings)  # noqa: E731
        raise ValueError(f"pred and gt bands were computed differently (pred: {describe(pred)}; gt: {describe(gt)}): "
                         "prepare the target with the loss's own settings")
    if pred.coeffs.approx.shape != gt.coeffs.approx.shape or pred.coeffs.levels != gt.coeffs.levels:
        raise ValueError(
            f"pred and gt decompose differently (pred image {pred.image_shape}, gt image {gt.image_shape}): "
            "give images of the same [B, C, H, W]"
        )
    if gt.device != pred.device or gt.dtype != pred.dtype:
        gt = gt.to(device=pred.device, dtype=pred.dtype)  # e.g. a float64 or CPU cache
    return gt


def _need(bands: WaveletBands, field: str, name: str) -> Tensor:
    value = getattr(bands, field)
    if value is None:
        raise ValueError(f"the {name} bands were computed without '{field}': compute them with wavelet_bands(..., "
                         f"{'kurtosis' if field != 'l_cov' else 'covariance'}=True)")
    return value


# --------------------------------------------------------------------------------------------------- losses


def _no_band_loss(pred: WaveletCoeffs) -> Tensor:
    """0 attached to pred's graph: the loss of an image too small for any DWT level (backward gives zeros)."""
    return pred.approx.sum() * 0.0


def wavelet_l1(pred: WaveletBands, gt: WaveletBands, wavelet_weighting: str = "paper") -> Tensor:
    """Scale-weighted L1 between detail subbands: sum_j w_j sum_{o in H,V,D} mean|c^j_o(pred) - c^j_o(gt)| (scalar)."""
    level_weights(0, wavelet_weighting)  # validate the name early
    gt = _check_pair(pred, gt)
    if pred.coeffs.levels == 0:
        return _no_band_loss(pred.coeffs)
    # sum over the 3 orientations of each one's mean = 3 * mean over the level's [B, C, 3, h, w]
    weights = [3.0 * weight for weight in level_weights(pred.coeffs.levels, wavelet_weighting)]
    if backend.compiled(pred.coeffs.approx):
        return _WeightedBandL1.apply(weights, [band.detach() for band in gt.coeffs.details], *pred.coeffs.details)
    loss = pred.coeffs.approx.new_zeros(())
    for weight, band_pred, band_gt in zip(weights, pred.coeffs.details, gt.coeffs.details):
        loss = loss + weight * F.l1_loss(band_pred, band_gt.detach())
    return loss


class _WeightedBandL1(torch.autograd.Function):
    """sum_j w_j mean|pred_j - gt_j| over the levels' detail bands on CPU, one compiled pass per level each way
    (float64 sums); the backward is w_j sign(pred_j - gt_j) / count_j, 0 where equal (torch's l1_loss)."""

    @staticmethod
    def forward(ctx, weights: list[float], targets: list[Tensor], *preds: Tensor) -> Tensor:
        from kc_splatfacto.losses._dwt_kernels import abs_difference_sum

        total = 0.0
        flat_pairs = []
        for weight, pred, target in zip(weights, preds, targets):
            pair = (pred.detach().contiguous().view(-1), target.contiguous().view(-1))
            total += weight * abs_difference_sum(pair[0].numpy(), pair[1].numpy()) / max(pair[0].numel(), 1)
            flat_pairs.append(pair)
        ctx.flat_pairs = flat_pairs
        ctx.weights = weights
        ctx.shapes = [pred.shape for pred in preds]
        return preds[0].new_tensor(total)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_loss: Tensor):
        from kc_splatfacto.losses._dwt_kernels import abs_difference_grad

        upstream = float(grad_loss.numpy())  # a CPU-only path (compiled kernels): read as their arrays are
        grads = []
        for weight, (pred, target), shape in zip(ctx.weights, ctx.flat_pairs, ctx.shapes):
            grad = torch.empty_like(pred)
            abs_difference_grad(pred.numpy(), target.numpy(), upstream * weight / max(pred.numel(), 1), grad.numpy())
            grads.append(grad.view(shape))
        return None, None, *grads


def kc_loss(pred: WaveletBands, gt: WaveletBands | None = None, kc_supervised: bool = True) -> Tensor:
    """Kurtosis-concentration loss (scalar), averaged over images and channels.

    supervised: |spread(pred) - spread(gt)| + sum_b |k_b(pred) - k_b(gt)|; unsupervised (gt unused): spread(pred).
    """
    if kc_supervised:
        if gt is None:
            raise ValueError("the supervised kc_loss needs gt (prepare_target(gt)); or pass kc_supervised=False")
        gt = _check_pair(pred, gt)
    if pred.coeffs.levels == 0:
        return _no_band_loss(pred.coeffs)
    k_pred, spread_pred = _need(pred, "kurtosis", "pred"), _need(pred, "spread", "pred")
    if not kc_supervised or gt is None:  # (gt is None only when unsupervised: checked above)
        return spread_pred.mean()
    per_image = (spread_pred - _need(gt, "spread", "gt")).abs() + (k_pred - _need(gt, "kurtosis", "gt")).abs().sum(dim=-1)
    return per_image.mean()


def cbc_loss(pred: WaveletBands, gt: WaveletBands | None = None, cbc_supervised: bool = True) -> Tensor:
    """Cross-band covariance loss (scalar), averaged over images and channels (covariance or correlation, as the
    bands were computed).

    supervised: |L_cov(pred) - L_cov(gt)|; unsupervised (gt unused): L_cov(pred).
    """
    if cbc_supervised:
        if gt is None:
            raise ValueError("the supervised cbc_loss needs gt (prepare_target(gt)); or pass cbc_supervised=False")
        gt = _check_pair(pred, gt, with_correlation=True)
    if pred.coeffs.levels == 0:
        return _no_band_loss(pred.coeffs)
    l_pred = _need(pred, "l_cov", "pred")
    if not cbc_supervised or gt is None:  # (gt is None only when unsupervised: checked above)
        return l_pred.mean()
    return (l_pred - _need(gt, "l_cov", "gt")).abs().mean()


def mean_band_kurtosis(bands: WaveletBands) -> list[float]:
    """Per-band excess kurtosis averaged over batch and channels, as 3J Python floats (level-major H, V, D): what the
    trainer logs."""
    return [float(v) for v in _need(bands, "kurtosis", "logged").detach().float().mean(dim=(0, 1)).cpu()]


# --------------------------------------------------------------------------------------------------- module


class FrequencyLoss(nn.Module):
    """The paper's three wavelet-domain terms, each already multiplied by its weight (parameters: the fields of
    :class:`FrequencyLossConfig`, whose defaults are the paper's).

    forward(pred [B, C, H, W], target: WaveletBands from :meth:`prepare_target`) -> dict holding only the terms whose
    weight is non-zero among "wavelet_loss", "kc_loss", "cbc_loss": one :func:`wavelet_bands` of pred, then
    :func:`wavelet_l1`, :func:`kc_loss`, :func:`cbc_loss`.
    """

    def __init__(
        self,
        wavelet_weight: float = _PAPER.wavelet_weight,
        kc_weight: float = _PAPER.kc_weight,
        cbc_weight: float = _PAPER.cbc_weight,
        wave: str = _PAPER.wave,
        wavelet_levels: int = _PAPER.wavelet_levels,
        wavelet_mode: str = _PAPER.wavelet_mode,
        wavelet_weighting: str = _PAPER.wavelet_weighting,
        kc_supervised: bool = _PAPER.kc_supervised,
        cbc_supervised: bool = _PAPER.cbc_supervised,
        cbc_correlation: bool = _PAPER.cbc_correlation,
    ) -> None:
        super().__init__()
        if wavelet_mode not in MODES:
            raise ValueError(f"unknown wavelet_mode '{wavelet_mode}': use one of {MODES}")
        level_weights(0, wavelet_weighting)
        for name, weight in (("wavelet_weight", wavelet_weight), ("kc_weight", kc_weight), ("cbc_weight", cbc_weight)):
            if not (math.isfinite(weight) and weight >= 0):
                raise ValueError(f"{name} must be a finite non-negative number, got {weight}")
        dwt2(torch.zeros(1, 1, 1, 1), wave=wave, levels=0)  # validates the wavelet name now, not at step 1
        self.wavelet_weight = float(wavelet_weight)
        self.kc_weight = float(kc_weight)
        self.cbc_weight = float(cbc_weight)
        self.wave = wave
        self.wavelet_levels = int(wavelet_levels)
        self.wavelet_mode = wavelet_mode
        self.wavelet_weighting = wavelet_weighting
        self.kc_supervised = kc_supervised
        self.cbc_supervised = cbc_supervised
        self.cbc_correlation = cbc_correlation
        self._warned_dropped_levels = False
        #: forward raises ValueError on a NaN/Inf ``pred`` (one host synchronisation on CUDA); a training loop that
        #: checks its whole step once after backward (kc-train's trainer) sets it False
        self.check_finite = True

    @property
    def config(self) -> FrequencyLossConfig:
        """This loss's settings."""
        return FrequencyLossConfig.from_fields(self)

    @property
    def active(self) -> bool:
        return self.config.active

    def bands(self, image: Tensor, kurtosis: bool = True, covariance: bool = True,
              check_finite: bool = True) -> WaveletBands:
        """:func:`wavelet_bands` of image [B, C, H, W] with this loss's settings."""
        self._warn_dropped_levels_once(image)
        return wavelet_bands(image, self.wave, self.wavelet_levels, self.wavelet_mode, self.cbc_correlation,
                             kurtosis=kurtosis, covariance=covariance, warn_dropped_levels=False,
                             check_finite=check_finite)

    def prepare_target(self, gt: Tensor) -> WaveletBands:
        """Detached bands and statistics of gt [B, C, H, W] with this loss's settings (cache it per image)."""
        self._warn_dropped_levels_once(gt)
        return prepare_target(gt, self.wave, self.wavelet_levels, self.wavelet_mode, self.cbc_correlation,
                              warn_dropped_levels=False)

    def _warn_dropped_levels_once(self, image: Tensor) -> None:
        """One warning per loss (i.e. per training run) when an image is too small for the requested levels, not one
        per image size: a resolution schedule changes the size several times."""
        if self._warned_dropped_levels or image.dim() != 4 or min(image.shape[-2:]) == 0:
            return
        height, width = image.shape[-2:]
        kept = supported_levels(height, width, self.wave, self.wavelet_levels)
        if kept < self.wavelet_levels:
            self._warned_dropped_levels = True
            warnings.warn(
                f"FrequencyLoss: a {height}x{width} image supports only {kept} of the {self.wavelet_levels} requested "
                f"{self.wave} levels; levels an image is too small for are left out (said once, for the first such "
                "size)",
                stacklevel=3,
            )

    def forward(self, pred: Tensor, target: WaveletBands) -> dict[str, Tensor]:
        if not self.active:
            return {}
        if not isinstance(target, WaveletBands):
            raise TypeError(f"target must be WaveletBands (FrequencyLoss.prepare_target(gt)), got {type(target).__name__}")
        _check_image(pred, "pred", finite=self.check_finite)
        if tuple(pred.shape) != tuple(target.image_shape):
            raise ValueError(
                f"pred {tuple(pred.shape)} and target {tuple(target.image_shape)} must have the same [B, C, H, W]"
            )
        bands = self.bands(pred, kurtosis=self.kc_weight > 0, covariance=self.cbc_weight > 0, check_finite=False)
        losses: dict[str, Tensor] = {}
        if self.wavelet_weight > 0:
            losses["wavelet_loss"] = self.wavelet_weight * wavelet_l1(bands, target, self.wavelet_weighting)
        if self.kc_weight > 0:
            losses["kc_loss"] = self.kc_weight * kc_loss(bands, target, self.kc_supervised)
        if self.cbc_weight > 0:
            losses["cbc_loss"] = self.cbc_weight * cbc_loss(bands, target, self.cbc_supervised)
        return losses
