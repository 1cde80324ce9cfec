"""Frequency-domain losses of KC-3DGS on the detail subbands of a J-level DWT (kornia style: functions + thin module).

Notation: c^j_o is the detail subband of level j (1 = finest) and orientation o in (H, V, D); b runs over the 3J
detail subbands in the order (level 1: H, V, D), (level 2: H, V, D), ...; every statistic is per image and channel.

- wavelet_l1      = sum_j w_j sum_o mean|c^j_o(pred) - c^j_o(gt)|,  w_j = 2^j ("paper"), 2^(J-j+1) ("fine"), 1 ("uniform")
- band_kurtosis   k_b = m4_b / (m2_b + eps)^2 - 3, m_k the central moments of subband b (scipy's biased Fisher kurtosis)
- kurtosis_spread = max_b k_b - min_b k_b
- kc_loss         = |spread(pred) - spread(gt)| + sum_b |k_b(pred) - k_b(gt)|        (unsupervised: spread(pred))
- covariance      Sigma^j = Z Z^T / (P - 1), Z the centred, flattened [3, P] stack of (H, V, D) of level j
                  (correlation option: Sigma_uv / sqrt((Sigma_uu + eps)(Sigma_vv + eps)))
- L_cov           = sum_j ||Sigma^j - diag(Sigma^j)||_F^2
- cbc_loss        = |L_cov(pred) - L_cov(gt)|                                         (unsupervised: L_cov(pred))
The kc and cbc terms are averaged over images and channels. `docs/losses.md` explains the choices (weighting, eps).

The ground truth never needs gradients: `prepare_target(gt)` computes its coefficients and statistics once, detached,
as a `WaveletTarget` that every loss here accepts in place of the gt image, so a trainer can cache it per image.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from kc_splatfacto.losses.wavelets import MODES, WaveletCoeffs, dwt2

WEIGHTINGS = ("paper", "fine", "uniform")
# eps on a band's variance, relative to the image's mean power (mean square over all its wavelet coefficients, which
# by Parseval is ~ the mean square pixel). 1e-12 in variance = a standard deviation of 1e-6 of the signal's RMS: ~10x
# above float32 rounding noise of the transform and ~4000x below an 8-bit quantization step, so every real band is
# untouched (a sigma-3 blurred photo's finest diagonal band, std 2e-5 RMS, keeps its kurtosis to 1%), while a
# constant or rounding-noise band (variance ~0) gets kurtosis -3 with a bounded gradient instead of 0/0. Being
# relative, it keeps every statistic exactly scale-invariant (intensities x1e4 or x1e-6 give the same kurtosis).
# docs/losses.md has the measured sweep.
VARIANCE_REL_EPS = 1e-12
# Absolute floor for an all-zero image (mean power 0), far above float32's smallest normal (~1e-38) when squared.
VARIANCE_ABS_EPS = 1e-30


def _check_finite(x: Tensor, name: str) -> None:
    if not bool(torch.isfinite(x).all()):
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


def _variance_eps(coeffs: WaveletCoeffs) -> Tensor:
    """[B, C, 1] eps on a band's variance: VARIANCE_REL_EPS times the image's mean coefficient power (detached)."""
    with torch.no_grad():
        total = coeffs.approx.square().sum(dim=(-2, -1))
        count = coeffs.approx.shape[-2] * coeffs.approx.shape[-1]
        for band in coeffs.details:
            total = total + band.square().sum(dim=(-4, -2, -1))
            count += band.shape[-3] * band.shape[-2] * band.shape[-1]
        return (VARIANCE_REL_EPS * total / count + VARIANCE_ABS_EPS).unsqueeze(-1)


def _centred_levels(coeffs: WaveletCoeffs) -> list[Tensor]:
    """Per level, the centred flattened subbands [B, C, 3, P_j]."""
    centred = []
    for band in coeffs.details:
        flat = band.flatten(-2)
        centred.append(flat - flat.mean(dim=-1, keepdim=True))
    return centred


def _kurtosis_from_centred(centred: list[Tensor], eps: Tensor) -> Tensor:
    kurtosis = []
    for z in centred:
        m2 = z.square().mean(dim=-1)  # [B, C, 3]
        # standardize first: (z / sqrt(m2 + eps))^4 keeps the 4th power in range where z^4 would underflow
        standardized = z * torch.rsqrt(m2 + eps).unsqueeze(-1)
        kurtosis.append(standardized.square().square().mean(dim=-1) - 3.0)
    if not kurtosis:
        return eps.new_zeros((*eps.shape[:-1], 0))
    return torch.cat(kurtosis, dim=-1)


def band_kurtosis(coeffs: WaveletCoeffs) -> Tensor:
    """Excess (Fisher, biased) kurtosis of every detail subband: [B, C, 3J], bands ordered level-major (H, V, D).

    k_b = m4_b / (m2_b + eps)^2 - 3 with central moments m_k; equals `scipy.stats.kurtosis(band, fisher=True,
    bias=True)` up to the relative eps (a constant band gives -3, not NaN).
    """
    return _kurtosis_from_centred(_centred_levels(coeffs), _variance_eps(coeffs))


def kurtosis_spread(kurtosis: Tensor) -> Tensor:
    """max_b k_b - min_b k_b over the last axis: [..., 3J] -> [...] (0 when there are no bands)."""
    if kurtosis.shape[-1] == 0:
        return kurtosis.sum(dim=-1)
    return kurtosis.amax(dim=-1) - kurtosis.amin(dim=-1)


def _covariances_from_centred(centred: list[Tensor], eps: Tensor, correlation: bool) -> list[Tensor]:
    covariances = []
    for z in centred:
        count = z.shape[-1]
        cov = z @ z.transpose(-1, -2) / max(count - 1, 1)  # [B, C, 3, 3]; numpy.cov's (P - 1) normalization
        if correlation:
            var = torch.diagonal(cov, dim1=-2, dim2=-1) + eps  # eps is a variance too (same scale)
            inv_std = torch.rsqrt(var)
            cov = cov * inv_std.unsqueeze(-1) * inv_std.unsqueeze(-2)
        covariances.append(cov)
    return covariances


def cross_band_covariance(coeffs: WaveletCoeffs, correlation: bool = False) -> list[Tensor]:
    """Per level (finest first), the 3x3 covariance (or correlation) of the centred (H, V, D) subbands: [B, C, 3, 3].

    Equals `numpy.cov(np.stack([cH, cV, cD]).reshape(3, -1))` (correlation: `numpy.corrcoef`, up to eps).
    """
    return _covariances_from_centred(_centred_levels(coeffs), _variance_eps(coeffs), correlation)


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

    def to(self, *args, **kwargs) -> "WaveletTarget":
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
        centred = _centred_levels(coeffs)
        eps = _variance_eps(coeffs)
        kurtosis = _kurtosis_from_centred(centred, eps)
        l_cov = _off_diagonal_energy(_covariances_from_centred(centred, eps, correlation), coeffs.approx)
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


def _as_coeffs(x, name: str, wave: str, levels: int, mode: str) -> WaveletCoeffs:
    if isinstance(x, WaveletCoeffs):
        return x
    if isinstance(x, WaveletTarget):
        return x.coeffs
    _check_image(x, name)
    return dwt2(x, wave=wave, levels=levels, mode=mode)


def _as_target(gt, wave: str, levels: int, mode: str, correlation: bool) -> WaveletTarget:
    if isinstance(gt, WaveletTarget):
        if (gt.wave, gt.levels, gt.mode, gt.correlation) != (wave, levels, mode, correlation):
            raise ValueError(
                f"the cached WaveletTarget was prepared with wave={gt.wave}, levels={gt.levels}, mode={gt.mode}, "
                f"correlation={gt.correlation}, but the loss uses wave={wave}, levels={levels}, mode={mode}, "
                f"correlation={correlation}: prepare the target with the loss's own settings"
            )
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


def _wavelet_l1_coeffs(pred: WaveletCoeffs, gt: WaveletCoeffs, weighting: str) -> Tensor:
    weights = level_weights(pred.levels, weighting)
    loss = pred.approx.new_zeros(())
    for weight, band_pred, band_gt in zip(weights, pred.details, gt.details):
        # sum over the 3 orientations of each one's mean = 3 * mean over the level's [B, C, 3, h, w]
        loss = loss + (weight * 3.0) * (band_pred - band_gt).abs().mean()
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
    k_pred = band_kurtosis(pred_c)
    if not supervised:
        return kurtosis_spread(k_pred).mean()
    if gt is None:
        raise ValueError("the supervised kc_loss needs gt (an image or a WaveletTarget); or pass supervised=False")
    if isinstance(gt, WaveletTarget):
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
    l_pred = covariance_penalty(pred_c, correlation)
    if not supervised:
        return l_pred.mean()
    if gt is None:
        raise ValueError("the supervised cbc_loss needs gt (an image or a WaveletTarget); or pass supervised=False")
    if isinstance(gt, WaveletTarget):
        if gt.correlation != correlation:
            raise ValueError(f"the WaveletTarget holds L_cov with correlation={gt.correlation}, not {correlation}")
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
            if not weight >= 0:
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
        if target.device != pred.device:
            target = target.to(pred.device)
        coeffs = dwt2(pred, wave=self.wave, levels=self.levels, mode=self.mode)
        losses: dict[str, Tensor] = {}
        if self.wavelet_weight > 0:
            losses["wavelet_loss"] = self.wavelet_weight * _wavelet_l1_coeffs(coeffs, target.coeffs, self.weighting)
        if self.kc_weight > 0 or self.cbc_weight > 0:
            centred = _centred_levels(coeffs)
            eps = _variance_eps(coeffs)
            if self.kc_weight > 0:
                k_pred = _kurtosis_from_centred(centred, eps)
                if self.kc_supervised:
                    kc = _kc_from_kurtosis(k_pred, target.kurtosis, target.spread)
                else:
                    kc = kurtosis_spread(k_pred).mean()
                losses["kc_loss"] = self.kc_weight * kc
            if self.cbc_weight > 0:
                l_pred = _off_diagonal_energy(
                    _covariances_from_centred(centred, eps, self.cbc_correlation), coeffs.approx
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
