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

The ground truth never needs gradients: `prepare_target(gt)` computes its coefficients and statistics once, detached,
as a `WaveletTarget` that every loss here accepts in place of the gt image, so a trainer can cache it per image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from kc_splatfacto.losses.wavelets import MODES, WaveletCoeffs, dwt2

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


def _check_finite(x: Tensor, name: str) -> None:
    # one reduction pass: a NaN/Inf anywhere makes the sum non-finite (only then is the exact check needed); the sum
    # is float32 at least, so a large half-precision image does not overflow into the slow path
    total = x.sum(dtype=torch.float32) if x.dtype in (torch.float16, torch.bfloat16) else x.sum()
    if not bool(torch.isfinite(total)) and not bool(torch.isfinite(x).all()):
        raise ValueError(
            f"'{name}' contains NaN or Inf values; the frequency losses need finite images "
            f"(check the renderer output / the loaded image for '{name}')"
        )


def _check_image(x: Tensor, name: str) -> None:
    if not isinstance(x, Tensor) or x.dim() != 4:
        shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        raise ValueError(f"'{name}' must be an image batch of shape [B, C, H, W], got {shape}")
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


class _CentredMoments(torch.autograd.Function):
    """Moments of centred, RMS-normalized subbands z = (x - mean(x)) / s of one level, with an analytic backward.

    x [N, 3, P] -> m2 [N, 3] = mean z^2, m4 [N, 3] = mean z^4 (if wanted), cov [N, 3, 3] = z z^T / (P - 1) (if wanted).
    Backward: dz = z (2 g2 + 4 g4 z^2) / P + (G + G^T) z / (P - 1), then dx = (dz - mean(dz)) / s. That is ~5 passes
    over the band where autograd through the elementwise chain takes ~12 (the losses' main cost after the DWT).
    s is a detached constant.
    """

    @staticmethod
    def forward(ctx, flat: Tensor, inv_rms: Tensor, want_m4: bool, want_cov: bool):
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
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_m2, grad_m4, grad_cov):
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


def _level_moments(coeffs: WaveletCoeffs, want_m4: bool, want_cov: bool) -> tuple[list[tuple], Tensor]:
    """Per level (m2 [B, C, 3], m4 or None, cov [B, C, 3, 3] or None) of the RMS-normalized centred subbands,
    and the image power s^2 [B, C, 1] they are normalized by."""
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


# --------------------------------------------------------------------------------------------------- target


@dataclass
class WaveletTarget:
    """Detached coefficients and statistics of a ground-truth batch (compute once per image, reuse every step).

    coeffs: WaveletCoeffs of gt; kurtosis [B, C, 3J]; spread [B, C]; l_cov [B, C] (with `correlation`);
    wave / levels (requested) / mode: the transform they were computed with; image_shape: gt's [B, C, H, W].
    """

    coeffs: WaveletCoeffs
    kurtosis: Tensor
    spread: Tensor
    l_cov: Tensor
    wave: str
    levels: int
    mode: str
    correlation: bool
    image_shape: tuple[int, int, int, int]

    def to(self, *args, **kwargs) -> WaveletTarget:
        return WaveletTarget(
            coeffs=self.coeffs.to(*args, **kwargs),
            kurtosis=self.kurtosis.to(*args, **kwargs),
            spread=self.spread.to(*args, **kwargs),
            l_cov=self.l_cov.to(*args, **kwargs),
            wave=self.wave,
            levels=self.levels,
            mode=self.mode,
            correlation=self.correlation,
            image_shape=self.image_shape,
        )

    @property
    def device(self) -> torch.device:
        return self.coeffs.approx.device


def prepare_target(
    gt: Tensor, wave: str = "db3", levels: int = 3, mode: str = "symmetric", correlation: bool = False
) -> WaveletTarget:
    """Detached WaveletTarget of gt [B, C, H, W] (raises ValueError on NaN/Inf naming 'gt')."""
    _check_image(gt, "gt")
    with torch.no_grad():
        coeffs = dwt2(gt.detach(), wave=wave, levels=levels, mode=mode)
        moments, power = _level_moments(coeffs, True, True)
        kurtosis = _kurtosis_from_moments(moments, coeffs.approx)
        l_cov = _off_diagonal_energy(_covariances_from_moments(moments, power, correlation), coeffs.approx)
    return WaveletTarget(
        coeffs=coeffs,
        kurtosis=kurtosis,
        spread=kurtosis_spread(kurtosis),
        l_cov=l_cov,
        wave=wave,
        levels=levels,
        mode=mode,
        correlation=correlation,
        image_shape=tuple(gt.shape),
    )


def _check_target_settings(target: WaveletTarget, wave: str, levels: int, mode: str, correlation: bool) -> None:
    if (target.wave, target.levels, target.mode, target.correlation) != (wave, levels, mode, correlation):
        raise ValueError(
            f"the cached WaveletTarget was prepared with wave={target.wave}, levels={target.levels}, "
            f"mode={target.mode}, correlation={target.correlation}, but the loss uses wave={wave}, levels={levels}, "
            f"mode={mode}, correlation={correlation}: prepare the target with the loss's own settings"
        )


def _as_coeffs(x, name: str, wave: str, levels: int, mode: str) -> WaveletCoeffs:
    if isinstance(x, WaveletCoeffs):
        return x
    if isinstance(x, WaveletTarget):
        _check_target_settings(x, wave, levels, mode, x.correlation)  # correlation only matters for L_cov
        return x.coeffs
    _check_image(x, name)
    return dwt2(x, wave=wave, levels=levels, mode=mode)


def _as_target(gt, wave: str, levels: int, mode: str, correlation: bool) -> WaveletTarget:
    if isinstance(gt, WaveletTarget):
        _check_target_settings(gt, wave, levels, mode, correlation)
        return gt
    if isinstance(gt, WaveletCoeffs):
        raise TypeError("pass the gt as an image [B, C, H, W] or a WaveletTarget (from prepare_target), not coeffs")
    return prepare_target(gt, wave=wave, levels=levels, mode=mode, correlation=correlation)


def _check_same_layout(pred: WaveletCoeffs, gt: WaveletCoeffs) -> None:
    if pred.approx.shape != gt.approx.shape or pred.levels != gt.levels:
        raise ValueError(
            f"pred and gt decompose differently (pred approx {tuple(pred.approx.shape)} with {pred.levels} levels, "
            f"gt approx {tuple(gt.approx.shape)} with {gt.levels} levels): give images of the same [B, C, H, W]"
        )


# --------------------------------------------------------------------------------------------------- losses


def _no_band_loss(pred: WaveletCoeffs) -> Tensor:
    """0 attached to pred's graph: the loss of an image too small for any DWT level (backward gives zeros)."""
    return pred.approx.sum() * 0.0


def _wavelet_l1_coeffs(pred: WaveletCoeffs, gt: WaveletCoeffs, weighting: str) -> Tensor:
    if pred.levels == 0:
        return _no_band_loss(pred)
    weights = level_weights(pred.levels, weighting)
    loss = pred.approx.new_zeros(())
    for weight, band_pred, band_gt in zip(weights, pred.details, gt.details):
        # sum over the 3 orientations of each one's mean = 3 * mean over the level's [B, C, 3, h, w]
        loss = loss + (weight * 3.0) * F.l1_loss(band_pred, band_gt)
    return loss


def wavelet_l1(
    pred, gt, weighting: str = "paper", wave: str = "db3", levels: int = 3, mode: str = "symmetric"
) -> Tensor:
    """Scale-weighted L1 between detail subbands: sum_j w_j sum_{o in H,V,D} mean|c^j_o(pred) - c^j_o(gt)| (scalar).

    pred: image [B, C, H, W] or its WaveletCoeffs; gt: image, WaveletCoeffs or WaveletTarget.
    """
    level_weights(0, weighting)  # validate the name early
    pred_c = _as_coeffs(pred, "pred", wave, levels, mode)
    gt_c = _as_coeffs(gt, "gt", wave, levels, mode)
    _check_same_layout(pred_c, gt_c)
    return _wavelet_l1_coeffs(pred_c, gt_c.detach(), weighting)


def kc_loss(
    pred, gt=None, supervised: bool = True, wave: str = "db3", levels: int = 3, mode: str = "symmetric"
) -> Tensor:
    """Kurtosis-concentration loss (scalar), averaged over images and channels.

    supervised: |spread(pred) - spread(gt)| + sum_b |k_b(pred) - k_b(gt)|; unsupervised (gt unused): spread(pred).
    """
    pred_c = _as_coeffs(pred, "pred", wave, levels, mode)
    if pred_c.levels == 0:
        return _no_band_loss(pred_c)
    k_pred = band_kurtosis(pred_c)
    if not supervised:
        return kurtosis_spread(k_pred).mean()
    if gt is None:
        raise ValueError("the supervised kc_loss needs gt (an image or a WaveletTarget); or pass supervised=False")
    if isinstance(gt, WaveletTarget):
        _check_target_settings(gt, wave, levels, mode, gt.correlation)
        k_gt, spread_gt = gt.kurtosis, gt.spread
    else:
        gt_c = _as_coeffs(gt, "gt", wave, levels, mode).detach()
        k_gt = band_kurtosis(gt_c)
        spread_gt = kurtosis_spread(k_gt)
    if k_gt.shape != k_pred.shape:
        raise ValueError(f"pred and gt kurtosis shapes differ: {tuple(k_pred.shape)} vs {tuple(k_gt.shape)}")
    return _kc_from_kurtosis(k_pred, k_gt, spread_gt)


def _kc_from_kurtosis(k_pred: Tensor, k_gt: Tensor, spread_gt: Tensor) -> Tensor:
    per_image = (kurtosis_spread(k_pred) - spread_gt).abs() + (k_pred - k_gt).abs().sum(dim=-1)
    return per_image.mean()


def cbc_loss(
    pred,
    gt=None,
    supervised: bool = True,
    correlation: bool = False,
    wave: str = "db3",
    levels: int = 3,
    mode: str = "symmetric",
) -> Tensor:
    """Cross-band covariance loss (scalar), averaged over images and channels.

    supervised: |L_cov(pred) - L_cov(gt)|; unsupervised (gt unused): L_cov(pred).
    """
    pred_c = _as_coeffs(pred, "pred", wave, levels, mode)
    if pred_c.levels == 0:
        return _no_band_loss(pred_c)
    l_pred = covariance_penalty(pred_c, correlation)
    if not supervised:
        return l_pred.mean()
    if gt is None:
        raise ValueError("the supervised cbc_loss needs gt (an image or a WaveletTarget); or pass supervised=False")
    if isinstance(gt, WaveletTarget):
        _check_target_settings(gt, wave, levels, mode, correlation)
        l_gt = gt.l_cov
    else:
        l_gt = covariance_penalty(_as_coeffs(gt, "gt", wave, levels, mode).detach(), correlation)
    return (l_pred - l_gt).abs().mean()


# --------------------------------------------------------------------------------------------------- module


class FrequencyLoss(nn.Module):
    """The paper's three wavelet-domain terms from ONE DWT of the prediction.

    forward(pred [B, C, H, W], target: WaveletTarget | gt image [B, C, H, W]) -> dict holding only the terms whose
    weight is non-zero among "wavelet_loss", "kc_loss", "cbc_loss", each already multiplied by its weight.
    Defaults are the paper's (supplementary hyperparameter table): wavelet 1e-3, kc 1e-5, cbc 1e-2, db3, 3 levels.
    """

    def __init__(
        self,
        wavelet_weight: float = 1e-3,
        kc_weight: float = 1e-5,
        cbc_weight: float = 1e-2,
        wave: str = "db3",
        levels: int = 3,
        mode: str = "symmetric",
        weighting: str = "paper",
        kc_supervised: bool = True,
        cbc_supervised: bool = True,
        cbc_correlation: bool = False,
    ) -> None:
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"unknown mode '{mode}': use one of {MODES}")
        level_weights(0, weighting)
        for name, weight in (("wavelet_weight", wavelet_weight), ("kc_weight", kc_weight), ("cbc_weight", cbc_weight)):
            if not (math.isfinite(weight) and weight >= 0):
                raise ValueError(f"{name} must be a finite non-negative number, got {weight}")
        dwt2(torch.zeros(1, 1, 1, 1), wave=wave, levels=0)  # validates the wavelet name now, not at step 1
        self.wavelet_weight = float(wavelet_weight)
        self.kc_weight = float(kc_weight)
        self.cbc_weight = float(cbc_weight)
        self.wave = wave
        self.levels = int(levels)
        self.mode = mode
        self.weighting = weighting
        self.kc_supervised = kc_supervised
        self.cbc_supervised = cbc_supervised
        self.cbc_correlation = cbc_correlation

    @property
    def active(self) -> bool:
        return self.wavelet_weight > 0 or self.kc_weight > 0 or self.cbc_weight > 0

    def prepare_target(self, gt: Tensor) -> WaveletTarget:
        """Detached coefficients and statistics of gt [B, C, H, W] with this loss's settings (cache it per image)."""
        return prepare_target(gt, self.wave, self.levels, self.mode, self.cbc_correlation)

    def band_kurtosis_for_logging(self, image_or_target) -> list[float]:
        """Per-band kurtosis averaged over batch and channels (3J floats), of an image or a WaveletTarget."""
        return band_kurtosis_for_logging(image_or_target, self.wave, self.levels, self.mode)

    def forward(self, pred: Tensor, target) -> dict[str, Tensor]:
        if not self.active:
            return {}
        _check_image(pred, "pred")
        if isinstance(target, Tensor):
            _check_image(target, "target")
        target = _as_target(target, self.wave, self.levels, self.mode, self.cbc_correlation)
        if tuple(pred.shape) != tuple(target.image_shape):
            raise ValueError(
                f"pred {tuple(pred.shape)} and target {tuple(target.image_shape)} must have the same [B, C, H, W]"
            )
        coeffs = dwt2(pred, wave=self.wave, levels=self.levels, mode=self.mode)
        reference = coeffs.approx
        if target.device != reference.device or target.coeffs.approx.dtype != reference.dtype:
            target = target.to(device=reference.device, dtype=reference.dtype)  # e.g. a float64 or CPU cache
        losses: dict[str, Tensor] = {}
        if self.wavelet_weight > 0:
            losses["wavelet_loss"] = self.wavelet_weight * _wavelet_l1_coeffs(coeffs, target.coeffs, self.weighting)
        if coeffs.levels == 0:  # too small for any level: every active term is an attached 0
            zero = _no_band_loss(coeffs)
            for key, weight in (("kc_loss", self.kc_weight), ("cbc_loss", self.cbc_weight)):
                if weight > 0:
                    losses[key] = zero
        elif self.kc_weight > 0 or self.cbc_weight > 0:
            moments, power = _level_moments(coeffs, self.kc_weight > 0, self.cbc_weight > 0)
            if self.kc_weight > 0:
                k_pred = _kurtosis_from_moments(moments, coeffs.approx)
                if self.kc_supervised:
                    kc = _kc_from_kurtosis(k_pred, target.kurtosis, target.spread)
                else:
                    kc = kurtosis_spread(k_pred).mean()
                losses["kc_loss"] = self.kc_weight * kc
            if self.cbc_weight > 0:
                l_pred = _off_diagonal_energy(
                    _covariances_from_moments(moments, power, self.cbc_correlation), coeffs.approx
                )
                cbc = (l_pred - target.l_cov).abs().mean() if self.cbc_supervised else l_pred.mean()
                losses["cbc_loss"] = self.cbc_weight * cbc
        return losses


def band_kurtosis_for_logging(
    image_or_target, wave: str = "db3", levels: int = 3, mode: str = "symmetric"
) -> list[float]:
    """Per-band excess kurtosis averaged over batch and channels, as 3J Python floats (level-major H, V, D).

    Accepts a WaveletTarget, an image [B, C, H, W] or a single image [H, W, C] (the model's rgb layout).
    """
    if isinstance(image_or_target, WaveletTarget):
        kurtosis = image_or_target.kurtosis
    else:
        image = image_or_target.detach()
        if image.dim() == 3:
            image = image.permute(2, 0, 1).unsqueeze(0)
        _check_image(image, "image")
        with torch.no_grad():
            kurtosis = band_kurtosis(dwt2(image, wave=wave, levels=levels, mode=mode))
    return [float(v) for v in kurtosis.detach().float().mean(dim=(0, 1)).cpu()]
