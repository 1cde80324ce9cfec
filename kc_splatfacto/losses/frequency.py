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
- lowpass_l1      = sum_j v_j mean|a^j(pred) - a^j(gt)| on the approximation (LL) bands of levels 1..J, v_j =
                  2^-(j-1) ("halving") or 1: not KC-3DGS, the low-pass supervision of DWTGS / LGDWT-GS
- diagonal_sparsity = mean|c^1_D(pred)|: the render's finest diagonal band (DWTGS's sparsity; no ground truth)
The kc and cbc terms are averaged over images and channels. An image too small for any level has no detail band:
every term is then 0 (still attached to pred's graph, with a zero gradient). `docs/losses.md` explains the choices
(weighting, padding, eps).

API (kornia's shape: functions that do the work, a thin module that calls them): `wavelet_bands(image)` computes an
image's DWT and statistics once (`WaveletBands`); `wavelet_l1`, `kc_loss` and `cbc_loss` take the bands of pred and
gt, so the three terms share one DWT of the render and KC and CBC one moment pass. The ground truth never needs
gradients: `prepare_target(gt)` is its bands, detached, which a trainer caches per image. `FrequencyLoss(pred,
target)` is `wavelet_bands(pred)` followed by the three functions, each times its weight.

This module holds the formulas; the passes over the subbands that carry them (moments, the band L1) and their
hand-written backwards, on the compiled CPU kernels or torch ops, are in `_frequency_autograd.py`. The settings and
their allowed ranges are :class:`FrequencyLossConfig`'s fields, written once: the module, the functions' defaults and
the model config (which nests this config) read them from there.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any, Literal

import torch
from torch import Tensor, nn

from kc_splatfacto import backend
from kc_splatfacto.losses import _fused_frequency as fused
from kc_splatfacto.losses._frequency_autograd import Moments, level_moments, weighted_band_l1
from kc_splatfacto.losses.layout import channels_first, composite_with_background
from kc_splatfacto.losses.wavelets import (
    VARIANCE_REL_EPS,
    WaveletCoeffs,
    dropped_levels_phrase,
    dwt2,
    supported_levels,
)
from kc_splatfacto.settings import check_settings, integer, real, setting

WaveName = Literal["haar", "db1", "db2", "db3", "db4", "db5", "db6", "db7", "db8", "db9", "db10"]
"""the orthogonal Daubechies wavelets the DWT has filters for (wavelets.MAX_DB_ORDER)"""
WaveletMode = Literal["symmetric", "reflect", "zero", "periodization"]
"""DWT boundary extensions (pywt's names; wavelets.MODES)"""
Weighting = Literal["paper", "fine", "uniform"]
WEIGHTINGS: tuple[str, ...] = Weighting.__args__  # type: ignore[attr-defined]
LowpassWeighting = Literal["halving", "uniform"]
LOWPASS_WEIGHTINGS: tuple[str, ...] = LowpassWeighting.__args__  # type: ignore[attr-defined]


@dataclass
class FrequencyLossConfig:
    """Settings of :class:`FrequencyLoss`, each with its allowed range; the defaults are the paper's (Method section;
    supplementary hyperparameter table): wavelet 1e-3 with 2^j level weights, KC 1e-5 and CBC 1e-2 both supervised,
    db3, 3 levels. The model config nests one (``pipeline.model.frequency``, every weight 0 for Splatfacto)."""

    wavelet_weight: float = setting(1e-3, real(0.0))
    """weight of the wavelet L1 on the detail subbands"""
    kc_weight: float = setting(1e-5, real(0.0))
    """weight of the kurtosis-concentration loss"""
    cbc_weight: float = setting(1e-2, real(0.0))
    """weight of the cross-band covariance loss"""
    wave: WaveName = "db3"
    """orthogonal Daubechies wavelet of the DWT"""
    wavelet_levels: int = setting(3, integer(0, 16))
    """DWT levels (fewer where the image is too small for them, with a warning)"""
    skip_finest_levels: int = setting(0, integer(0, 15))
    """finest DWT levels of the full-size training image left out of every term (the scene plan's 'levels': their
    detail is at the images' noise floor): their bands are not compared; at a warm-up stage of 1/2^d resolution d
    fewer are left out (the downscale has averaged that noise away; :attr:`FrequencyLoss.downscale`). 0: every level"""
    wavelet_mode: WaveletMode = "symmetric"
    """DWT boundary extension (pywt's names; docs/losses.md measures why symmetric)"""
    wavelet_weighting: Weighting = "paper"
    """per-level weights of the wavelet L1: 'paper' 2^j (j=1 finest), 'fine' 2^(J-j+1), 'uniform' 1"""
    kc_supervised: bool = True
    """KC compares the render's band kurtosis with the GT's (False: the unsupervised spread of the render alone)"""
    cbc_supervised: bool = True
    """CBC compares the render's cross-band covariance with the GT's (False: the render's alone)"""
    cbc_correlation: bool = False
    """CBC on band correlations instead of covariances (the 'scaled CBC' ablation)"""
    lowpass_weight: float = setting(0.0, real(0.0))
    """weight of the L1 on the approximation (LL) bands of levels 1..J (not KC-3DGS: the low-pass supervision of
    DWTGS and LGDWT-GS)"""
    lowpass_weighting: LowpassWeighting = "halving"
    """per-level weights of the low-pass L1: 'halving' 2^-(j-1) (LGDWT-GS's 1, 0.5 for LL1, LL2), 'uniform' 1"""
    sparsity_weight: float = setting(0.0, real(0.0))
    """weight of the L1 sparsity of the render's finest diagonal (HH) band (DWTGS; no ground truth in it)"""

    @classmethod
    def off(cls) -> FrequencyLossConfig:
        """Every weight zero (Splatfacto), the paper's DWT settings kept for the logged band kurtosis."""
        weights: dict[str, Any] = {term.weight_field: 0.0 for term in TERMS}
        return cls(**weights)

    def active_terms(self) -> list[tuple[FrequencyTerm, float]]:
        """The terms of :data:`TERMS` whose weight is non-zero, with their weight."""
        return [(term, weight) for term in TERMS if (weight := getattr(self, term.weight_field)) > 0]

    @property
    def active(self) -> bool:
        """Whether any term has a non-zero weight (with every weight zero the loss is off: Splatfacto)."""
        return bool(self.active_terms())

    def field_conflict(self) -> tuple[str, str] | None:
        """A DWT level is needed while a term is on: (the field at fault, what it must be), or None."""
        if self.active and self.wavelet_levels < 1:
            weights = ", ".join(f"{term.weight_field} {weight!r}" for term, weight in self.active_terms())
            return "wavelet_levels", f"an integer >= 1 while a wavelet, KC or CBC weight is non-zero (here {weights})"
        if self.active and self.skip_finest_levels >= self.wavelet_levels:
            return "skip_finest_levels", (f"below wavelet_levels ({self.wavelet_levels}) while a term is on: at least "
                                          "the coarsest level is compared")
        return None

    def setup(self) -> FrequencyLoss:
        """The loss module these settings describe (checked: a value outside its range raises ValueError)."""
        return FrequencyLoss(self)


_PAPER = FrequencyLossConfig()
"""the paper's settings: the defaults of the function API below"""


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


def _asked(moment: Tensor | None, name: str) -> Tensor:
    if moment is None:  # a caller bug: level_moments computes only the moments asked for
        raise RuntimeError(f"the band moment {name} was not computed")
    return moment


def _kurtosis_from_moments(moments: list[Moments], like: Tensor) -> Tensor:
    """k_b = m4_b / (m2_b + eps)^2 - 3 for every band, [B, C, 3J]; the moments are of c / s, so O(1) whatever the
    image's scale (m4 neither overflows nor underflows where it matters) and eps is relative to s^2."""
    if not moments:
        return like.new_zeros((*like.shape[:2], 0))
    # the levels joined first: the formula's ops run once, not once per level (on a GPU, where the step is bound by
    # kernel launches); elementwise, so the same values to the bit
    m2 = torch.cat([m2 for m2, _, _ in moments], dim=-1)
    m4 = torch.cat([_asked(m4, "m4") for _, m4, _ in moments], dim=-1)
    return m4 / (m2 + VARIANCE_REL_EPS).square() - 3.0


def band_kurtosis(coeffs: WaveletCoeffs) -> Tensor:
    """Excess (Fisher, biased) kurtosis of every detail subband: [B, C, 3J], bands ordered level-major (H, V, D).

    k_b = m4_b / (m2_b + eps s^2)^2 - 3 with central moments m_k and s^2 the image's mean coefficient power; equals
    `scipy.stats.kurtosis(band, fisher=True, bias=True)` up to the relative eps (a constant band gives -3, not NaN).
    """
    return _kurtosis_from_moments(level_moments(coeffs, True, False)[0], coeffs.approx)


def kurtosis_spread(kurtosis: Tensor) -> Tensor:
    """max_b k_b - min_b k_b over the last axis: [..., 3J] -> [...] (0 when there are no bands)."""
    if kurtosis.shape[-1] == 0:
        return kurtosis.sum(dim=-1)
    return kurtosis.amax(dim=-1) - kurtosis.amin(dim=-1)


def _covariances_from_moments(moments: list[Moments], power: Tensor, correlation: bool) -> Tensor:
    """Sigma^j = s^2 cov(c / s) of every level, stacked finest first: [J, B, C, 3, 3] (correlation: Sigma_uv /
    sqrt((Sigma_uu + eps)(Sigma_vv + eps)), scale-free, so computed on c / s directly). The levels are stacked before
    the formula, which then runs once (see :func:`_kurtosis_from_moments`)."""
    if not moments:
        return power.new_zeros((0, *power.shape[:2], 3, 3))
    cov = torch.stack([_asked(normalized, "cov") for _, _, normalized in moments])
    if correlation:
        inv_std = torch.rsqrt(torch.diagonal(cov, dim1=-2, dim2=-1) + VARIANCE_REL_EPS)
        return cov * inv_std.unsqueeze(-1) * inv_std.unsqueeze(-2)
    return cov * power.unsqueeze(-1)  # undo the normalization: cov(c) = s^2 cov(c / s)


def cross_band_covariance(coeffs: WaveletCoeffs, correlation: bool = False) -> list[Tensor]:
    """Per level (finest first), the 3x3 covariance (or correlation) of the centred (H, V, D) subbands: [B, C, 3, 3].

    Equals `numpy.cov(np.stack([cH, cV, cD]).reshape(3, -1))` (correlation: `numpy.corrcoef`, up to eps).
    """
    return list(_level_covariances(coeffs, correlation).unbind(0))


def _level_covariances(coeffs: WaveletCoeffs, correlation: bool) -> Tensor:
    """:func:`cross_band_covariance` stacked: [J, B, C, 3, 3]."""
    return _covariances_from_moments(*level_moments(coeffs, False, True), correlation)


def _off_diagonal_energy(covariances: Tensor) -> Tensor:
    """sum_j ||Sigma^j - diag(Sigma^j)||_F^2 of stacked covariances [J, B, C, 3, 3]: [B, C]."""
    off_diagonal = covariances - torch.diag_embed(torch.diagonal(covariances, dim1=-2, dim2=-1))
    return off_diagonal.square().sum(dim=(-2, -1)).sum(dim=0)


def covariance_penalty(coeffs: WaveletCoeffs, correlation: bool = False) -> Tensor:
    """L_cov = sum over levels of the squared off-diagonal Frobenius norm of the cross-band covariance: [B, C]."""
    return _off_diagonal_energy(_level_covariances(coeffs, correlation))


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
    skipped_levels: int = 0
    """finest levels left out: ``coeffs`` holds levels skipped_levels + 1 .. J (``skip_finest_levels`` at this size)"""
    image: Tensor | None = dataclasses.field(default=None, repr=False, compare=False)
    """the (detached) image of a target prepared off the compiled CPU kernels: the fused path computes its side of
    the terms with the same operations as the render's, so equal images give exactly zero"""
    slot_targets: dict[Any, fused.SlotTarget] = dataclasses.field(default_factory=dict, repr=False, compare=False)
    """these bands in the fused path's slot layout, per plan and L1 weights (filled by FrequencyLoss on first use)"""

    def to(self, *args, **kwargs) -> WaveletBands:
        def move(x: Tensor | None) -> Tensor | None:
            return None if x is None else x.to(*args, **kwargs)

        return dataclasses.replace(self, coeffs=self.coeffs.to(*args, **kwargs), kurtosis=move(self.kurtosis),
                                   spread=move(self.spread), l_cov=move(self.l_cov), image=move(self.image),
                                   slot_targets={})

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
    skip_finest_levels: int = 0,
) -> WaveletBands:
    """The DWT of image [B, C, H, W] and, when asked, its band kurtosis and L_cov (differentiable; raises
    ValueError on NaN/Inf unless ``check_finite`` is False); the statistics not asked for stay None. Levels the image
    is too small for are left out (with :func:`dwt2`'s warning unless ``warn_dropped_levels`` is False), and so are
    the ``skip_finest_levels`` finest: the DWT computes them (a coarser level is the DWT of a finer one's
    approximation) but no statistic or term reads their bands."""
    _check_image(image, "image", finite=check_finite)
    coeffs = dwt2(image, wave=wave, levels=wavelet_levels, mode=wavelet_mode, warn=warn_dropped_levels)
    if skip_finest_levels:
        coeffs = coeffs.without_finest(skip_finest_levels)
    k = spread = l_cov = None
    if kurtosis or covariance:  # (no level: empty kurtosis [B, C, 0], zero spread and L_cov)
        moments, power = level_moments(coeffs, kurtosis, covariance)
        if kurtosis:
            k = _kurtosis_from_moments(moments, coeffs.approx)
            spread = kurtosis_spread(k)
        if covariance:
            l_cov = _off_diagonal_energy(_covariances_from_moments(moments, power, cbc_correlation))
    return WaveletBands(coeffs, k, spread, l_cov, wave, wavelet_levels, wavelet_mode, cbc_correlation,
                        tuple(image.shape), skip_finest_levels)


def prepare_target(
    gt: Tensor,
    wave: str = _PAPER.wave,
    wavelet_levels: int = _PAPER.wavelet_levels,
    wavelet_mode: str = _PAPER.wavelet_mode,
    cbc_correlation: bool = _PAPER.cbc_correlation,
    warn_dropped_levels: bool = True,
    skip_finest_levels: int = 0,
) -> WaveletBands:
    """The ground truth's WaveletBands with every statistic, detached: compute once per image, reuse every step
    (raises ValueError on NaN/Inf naming 'gt')."""
    _check_image(gt, "gt")
    with torch.no_grad():
        bands = wavelet_bands(gt.detach(), wave, wavelet_levels, wavelet_mode, cbc_correlation,
                              warn_dropped_levels=warn_dropped_levels, skip_finest_levels=skip_finest_levels)
    if not backend.compiled(gt):
        bands.image = gt.detach()
    return bands


def _check_pair(pred: WaveletBands, gt: WaveletBands, with_correlation: bool = False) -> WaveletBands:
    """gt on pred's device and dtype, after checking that both were computed the same way."""
    for name, x in (("pred", pred), ("gt", gt)):
        if not isinstance(x, WaveletBands):
            raise TypeError(f"'{name}' must be WaveletBands (wavelet_bands(image) / prepare_target(gt)), "
                            f"got {type(x).__name__}")
    settings = ("wave", "wavelet_levels", "wavelet_mode", "skipped_levels") + (
        ("cbc_correlation",) if with_correlation else ())
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
    skipped = pred.skipped_levels  # the weights stay those of the levels' own indices j
    weights = [3.0 * weight for weight in level_weights(skipped + pred.coeffs.levels, wavelet_weighting)[skipped:]]
    return weighted_band_l1(weights, pred.coeffs.details, gt.coeffs.details)


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


def lowpass_level_weights(levels: int, lowpass_weighting: str = "halving") -> list[float]:
    """Per-level weights v_1..v_J (level 1 = finest) of the low-pass L1."""
    if lowpass_weighting == "halving":
        return [2.0 ** -(j - 1) for j in range(1, levels + 1)]
    if lowpass_weighting == "uniform":
        return [1.0] * levels
    raise ValueError(f"unknown low-pass weighting '{lowpass_weighting}': use one of {LOWPASS_WEIGHTINGS}")


def lowpass_l1(pred: WaveletBands, gt: WaveletBands, lowpass_weighting: str = "halving") -> Tensor:
    """L1 between the approximation (LL) bands of every level: sum_j v_j mean|a^j(pred) - a^j(gt)| (scalar).

    The orthonormal transform's a^j is about 2^j times the local mean of the image (each level's low-pass gains 2 in
    2D), so a level's term weighs its band's scale as well as v_j.
    """
    lowpass_level_weights(0, lowpass_weighting)  # validate the name early
    gt = _check_pair(pred, gt)
    if pred.coeffs.levels == 0:
        return _no_band_loss(pred.coeffs)
    skipped = pred.skipped_levels
    weights = lowpass_level_weights(skipped + pred.coeffs.levels, lowpass_weighting)[skipped:]
    terms = [weight * (band - target.detach()).abs().mean()
             for weight, band, target in zip(weights, pred.coeffs.approximations, gt.coeffs.approximations)]
    return torch.stack(terms).sum()


def diagonal_sparsity(pred: WaveletBands) -> Tensor:
    """mean|c^1_D(pred)|: the L1 of the finest diagonal (HH) band of the render (scalar; no ground truth)."""
    if pred.coeffs.levels == 0:
        return _no_band_loss(pred.coeffs)
    return pred.coeffs.details[0][:, :, 2].abs().mean()


# --------------------------------------------------------------------------------------------------- the table


@dataclass(frozen=True)
class FrequencyTerm:
    """One term of :class:`FrequencyLoss`: its name in a loss dictionary, the :class:`FrequencyLossConfig` field that
    holds its weight, the function it is of the render's and the ground truth's bands and the settings, the band
    statistics that function reads (``"kurtosis"``, ``"covariance"``: computed only when an active term needs them),
    and for which settings the fused Function (``_fused_frequency``, the torch path a GPU runs) computes it: None
    where it has no kernel there (the term then runs level by level, the fused terms beside it stay fused; a term
    marked fused must be one of ``_fused_frequency.OUTPUTS``, :func:`check_terms`)."""

    name: str
    weight_field: str
    function: Callable[[WaveletBands, WaveletBands, FrequencyLossConfig], Tensor]
    statistics: tuple[str, ...] = ()
    fused: Callable[[FrequencyLossConfig], bool] | None = None


TERMS: tuple[FrequencyTerm, ...] = (
    FrequencyTerm("wavelet_loss", "wavelet_weight", lambda pred, gt, c: wavelet_l1(pred, gt, c.wavelet_weighting),
                  fused=lambda c: True),
    FrequencyTerm("kc_loss", "kc_weight", lambda pred, gt, c: kc_loss(pred, gt, c.kc_supervised), ("kurtosis",),
                  fused=lambda c: c.kc_supervised),
    FrequencyTerm("cbc_loss", "cbc_weight", lambda pred, gt, c: cbc_loss(pred, gt, c.cbc_supervised), ("covariance",),
                  fused=lambda c: c.cbc_supervised and not c.cbc_correlation),
    FrequencyTerm("lowpass_loss", "lowpass_weight", lambda pred, gt, c: lowpass_l1(pred, gt, c.lowpass_weighting)),
    FrequencyTerm("sparsity_loss", "sparsity_weight", lambda pred, gt, c: diagonal_sparsity(pred)),
)
"""The frequency loss's terms: a new term is one entry here (a weight field on FrequencyLossConfig, a function of
the bands); "is any term active", "all off" and the weight names follow from this table."""
WEIGHTS = tuple(term.weight_field for term in TERMS)
"""the weight fields of :data:`TERMS`, in order"""


def check_terms(terms: tuple[FrequencyTerm, ...]) -> None:
    """Raises ValueError where a term is marked fused (``fused`` not None) but the fused Function does not compute it:
    its output would otherwise be missing from the loss, silently."""
    for term in terms:
        if term.fused is not None and term.name not in fused.OUTPUTS:
            raise ValueError(f"the frequency term '{term.name}' is marked fused, but the fused Function computes only "
                             f"{', '.join(fused.OUTPUTS)} (losses/_fused_frequency.py): give its FrequencyTerm "
                             "fused=None (it then runs level by level, the fused terms beside it stay fused) or "
                             "add it to FusedFrequencyTerms")


# --------------------------------------------------------------------------------------------------- module


class FrequencyLoss(nn.Module):
    """The paper's three wavelet-domain terms, each already multiplied by its weight.

    Built from a :class:`FrequencyLossConfig` (default: the paper's), any of its fields overridden by name:
    ``FrequencyLoss()``, ``FrequencyLoss(config)``, ``FrequencyLoss(kc_weight=0.0)``. A value outside its range or
    choices raises ValueError, an unknown name TypeError.

    forward(pred [B, C, H, W], target: WaveletBands from :meth:`prepare_target`) -> dict holding only the terms whose
    weight is non-zero among "wavelet_loss", "kc_loss", "cbc_loss": one :func:`wavelet_bands` of pred, then
    :func:`wavelet_l1`, :func:`kc_loss`, :func:`cbc_loss`.

    >>> loss = FrequencyLoss()
    >>> pred, gt = torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64)
    >>> sorted(loss(pred, loss.prepare_target(gt)))
    ['cbc_loss', 'kc_loss', 'wavelet_loss']
    """

    def __init__(self, config: FrequencyLossConfig | None = None, /, **settings: Any) -> None:
        super().__init__()
        config = dataclasses.replace(config if config is not None else FrequencyLossConfig(), **settings)
        check_settings(config, "FrequencyLoss")
        self.config = config
        #: a warning (once per image size) when an image is too small for the requested levels; a caller that says it
        #: in its own terms (kc-train's model names the training resolution) sets it False
        self.warn_dropped_levels = True
        self._warned_sizes: set[tuple[int, int]] = set()
        #: forward raises ValueError on a NaN/Inf ``pred`` (one host synchronisation on CUDA); a training loop that
        #: checks its whole step once after backward (kc-train's trainer) sets it False
        self.check_finite = True
        #: off the compiled CPU kernels (a GPU), the supervised terms in one autograd Function of few operations
        #: (``_fused_frequency``); False: level by level, as on the CPU (the tests compare the two)
        self.fused = True
        #: the training resolution's divisor 2^d (a model's resolution schedule sets it each step): the
        #: ``skip_finest_levels`` of the full-size image are d fewer here (:attr:`skipped_levels`)
        self.downscale = 1
        self._l1_weights: dict[Any, Tensor] = {}
        self._targets: dict[Hashable, WaveletBands] = {}  # the ground truths' targets by key (compare, target)
        check_terms(TERMS)

    @property
    def active(self) -> bool:
        return self.config.active

    @property
    def skipped_levels(self) -> int:
        """The finest levels left out at the current :attr:`downscale`: ``skip_finest_levels`` - d at 1/2^d (a
        halving is one level: the full-size image's level j is about level j - d of the downscaled one)."""
        return max(0, self.config.skip_finest_levels - (int(self.downscale).bit_length() - 1))

    def bands(self, image: Tensor, kurtosis: bool = True, covariance: bool = True,
              check_finite: bool = True, every_level: bool = False) -> WaveletBands:
        """:func:`wavelet_bands` of image [B, C, H, W] with this loss's settings (``every_level``: none of the
        finest left out, as the logged band kurtosis wants)."""
        self._warn_dropped_levels_once(image)
        c = self.config
        return wavelet_bands(image, c.wave, c.wavelet_levels, c.wavelet_mode, c.cbc_correlation,
                             kurtosis=kurtosis, covariance=covariance, warn_dropped_levels=False,
                             check_finite=check_finite, skip_finest_levels=0 if every_level else self.skipped_levels)

    def prepare_target(self, gt: Tensor) -> WaveletBands:
        """Detached bands and statistics of gt [B, C, H, W] with this loss's settings (cache it per image and
        resolution)."""
        self._warn_dropped_levels_once(gt)
        c = self.config
        return prepare_target(gt, c.wave, c.wavelet_levels, c.wavelet_mode, c.cbc_correlation,
                              warn_dropped_levels=False, skip_finest_levels=self.skipped_levels)

    def _warn_dropped_levels_once(self, image: Tensor) -> None:
        """One warning per image size (W x H) too small for the requested levels, none with
        ``warn_dropped_levels`` False."""
        if not self.warn_dropped_levels or image.dim() != 4 or min(image.shape[-2:]) == 0:
            return
        height, width = (int(n) for n in image.shape[-2:])
        if (width, height) in self._warned_sizes:
            return
        wave, levels = self.config.wave, self.config.wavelet_levels
        kept = supported_levels(height, width, wave, levels)
        if kept < levels:
            self._warned_sizes.add((width, height))
            warnings.warn(
                f"FrequencyLoss: a {width}x{height} image (W x H) supports only {kept} of the {levels} requested "
                f"{wave} levels; {dropped_levels_phrase(levels - kept, levels)} left out at that size",
                stacklevel=3,
            )

    def forward(self, pred: Tensor, target: WaveletBands) -> dict[str, Tensor]:
        if not self.config.active:
            return {}
        return self._stage(pred, target).losses(pred)

    def stage(self, pred: Tensor, gt: Tensor, key: Hashable | None = None) -> FrequencyStage:
        """The active terms of pred [B, C, H, W] against gt [B, C, H, W] (its target cached under ``key``, as
        :meth:`target`), split for a training step: :class:`FrequencyStage`. What an image loss that captures the
        fused terms in a CUDA graph calls (``model/image_loss.py``); ``stage(...).losses(pred)`` is :meth:`forward`.
        Raises as :meth:`forward` does on a bad ``pred``."""
        return self._stage(pred, self.target(gt, key))

    def _stage(self, pred: Tensor, target: WaveletBands) -> FrequencyStage:
        if not isinstance(target, WaveletBands):
            raise TypeError(f"target must be WaveletBands (FrequencyLoss.prepare_target(gt)), got {type(target).__name__}")
        _check_image(pred, "pred", finite=self.check_finite)
        if tuple(pred.shape) != tuple(target.image_shape):
            raise ValueError(
                f"pred {tuple(pred.shape)} and target {tuple(target.image_shape)} must have the same [B, C, H, W]"
            )
        fused_terms, level_terms = self.split_terms(pred)
        names = tuple(term.name for term, _ in fused_terms)
        setup = self._fused_setup(pred, target, names) if fused_terms else None
        if setup is None:  # no fused term, or an image too small for any level: the level-by-level zero loss
            return FrequencyStage(self, target, (), tuple(fused_terms) + tuple(level_terms), ())
        plan, slots, l1_weights = setup
        # the slot target's tensors the fused terms read, in fused.OUTPUTS' order (each is computed when its term is)
        read = zip(fused.OUTPUTS, (slots.weighted_bands, slots.kurtosis, slots.l_cov))
        tensors = tuple(fused._present(t) for name, t in read if name in names)
        return FrequencyStage(self, target, names, tuple(level_terms), tensors, plan, l1_weights)

    def split_terms(self, pred: Tensor) -> tuple[list[tuple[FrequencyTerm, float]], list[tuple[FrequencyTerm, float]]]:
        """The active terms (with their weights) as (those the fused Function computes for ``pred``, those computed
        level by level). A term is fused where its ``fused`` says so for these settings, off the compiled CPU kernels
        and with every level compared (the fused Function has no notion of a left-out finest level)."""
        check_terms(TERMS)
        active = self.config.active_terms()
        if not (self.fused and not backend.compiled(pred) and self.skipped_levels == 0):
            return [], active
        takes = [term.fused is not None and term.fused(self.config) for term, _ in active]
        return ([pair for pair, here in zip(active, takes) if here],
                [pair for pair, here in zip(active, takes) if not here])

    def takes_fused_path(self, pred: Tensor) -> bool:
        """Whether :meth:`forward` computes every active term of ``pred`` with the fused Function."""
        fused_terms, level_terms = self.split_terms(pred)
        return bool(fused_terms) and not level_terms

    # ------------------------------------------------------------------------------------------- one call per image
    def compare(self, render: Tensor, gt: Tensor, *, background: Tensor | None = None, mask: Tensor | None = None,
                key: Hashable | None = None) -> dict[str, Tensor]:
        """The active terms of a render against its ground truth, in the layout renders come in: what a training
        loop calls once per step.

        Args:
            render: [H, W, 3] or [B, H, W, 3] in [0, 1] (the rasterizer's layout).
            gt: the same shape, or RGBA [..., 4] (straight alpha) composited here over ``background`` [3] (the
                render's background, as nerfstudio composites).
            mask: [H, W, 1] or [B, H, W, 1], 1 where the pixel counts: render and ground truth are multiplied by it.
            key: the ground truth's identity (e.g. (image index, resolution)): its wavelet target is computed once
                per key and cached here. None: computed afresh (a ground truth that changes between visits, e.g.
                RGBA over a random background).

        >>> loss = FrequencyLoss()
        >>> render, gt = torch.rand(32, 48, 3), torch.rand(32, 48, 3)
        >>> sorted(loss.compare(render, gt, key=0))
        ['cbc_loss', 'kc_loss', 'wavelet_loss']
        """
        if not self.config.active:
            return {}
        gt = gt.to(device=render.device, dtype=render.dtype)
        if gt.shape[-1] == 4:
            if background is None:
                raise ValueError("an RGBA ground truth needs the background the render was composited over "
                                 "(compare(..., background=...))")
            gt = composite_with_background(gt, background)
        if gt.shape != render.shape:
            raise ValueError(f"render {tuple(render.shape)} and ground truth {tuple(gt.shape)} must have the same "
                             "[..., H, W, 3]")
        if mask is not None:
            mask = mask.to(render)
            render, gt = render * mask, gt * mask
        return self(channels_first(render), self.target(channels_first(gt), key))

    def target(self, gt: Tensor, key: Hashable | None = None) -> WaveletBands:
        """:meth:`prepare_target` of gt [B, C, H, W], cached under ``key`` (None: not cached)."""
        if key is None:
            return self.prepare_target(gt)
        target = self._targets.get(key)
        if target is None:
            target = self._targets[key] = self.prepare_target(gt)
        return target

    def cached_target(self, key: Hashable | None) -> WaveletBands | None:
        """The target cached under ``key`` by :meth:`compare` / :meth:`target`, or None (never computes one)."""
        return None if key is None else self._targets.get(key)

    def _fused_setup(self, pred: Tensor, target: WaveletBands, names: tuple[str, ...]
                     ) -> tuple[fused.BandPlan, fused.SlotTarget, Tensor | None] | None:
        """(plan, the target's slot form, the L1 weights) of the fused terms ``names`` for an image like pred [B, C,
        H, W] (its size, device and compute dtype): built on first use, then cached; None when the image supports no
        DWT level."""
        c = self.config
        dtype, device = _compute_dtype(pred.dtype), pred.device
        batch, channels, height, width = pred.shape
        planes = batch * channels
        plan = fused.plan_for((height, width), c.wave, c.wavelet_mode, c.wavelet_levels, pred.new_empty((), dtype=dtype))
        if plan is None:
            return None
        settings = ("wave", "wavelet_levels", "wavelet_mode") + (("cbc_correlation",) if "cbc_loss" in names else ())
        if target.skipped_levels or any(getattr(target, name) != getattr(c, name) for name in settings):
            raise ValueError("the target's bands were computed with other settings than this loss's: prepare the "
                             "target with the loss's own settings (FrequencyLoss.prepare_target)")
        if target.device != device or target.dtype != dtype:
            target = target.to(device=device, dtype=dtype)
        weights = None
        if "wavelet_loss" in names:
            key = (id(plan), planes)
            weights = self._l1_weights.get(key)
            if weights is None:
                per_level = level_weights(plan.levels, c.wavelet_weighting)
                weights = self._l1_weights[key] = fused.l1_slot_weights(plan, per_level, c.wavelet_weight, planes)
        slot_key = (id(plan), weights is not None, c.wavelet_weight, c.wavelet_weighting)
        slots = target.slot_targets.get(slot_key)
        if slots is None:
            if target.image is not None:
                gt = fused.as_planes(target.image.to(dtype))
                slots = fused.slot_target_of_image(gt, plan, weights)
            else:
                slots = fused.slot_target(target.coeffs.details, target.kurtosis, target.spread, target.l_cov, plan,
                                          weights)
            target.slot_targets[slot_key] = slots
        return plan, slots, weights


@dataclass(frozen=True)
class FrequencyStage:
    """The active terms of one render, split for a training step (:meth:`FrequencyLoss.stage`).

    The terms with a fused kernel (their :data:`TERMS` entry's ``fused``) are one function of tensors only,
    ``fused(pred, *tensors)``: the render and the ground truth's side in, the terms out, nothing read back to the
    host, so a CUDA graph can capture it. The rest run level by level, ``level_by_level(pred)``, beside it.
    ``combine(fused_outputs, pred)`` joins the two in the table's order; ``losses(pred)`` is the whole
    (:meth:`FrequencyLoss.forward`).

    fused_names: the fused terms, in the order ``fused`` returns them (empty on the compiled CPU kernels);
    level_terms: (term, weight) of the others; tensors: the ground truth's side of the fused terms (its slot form);
    graph_key: what a capture of ``fused`` is specific to (the image size's plan, the tensors' shapes, the terms).
    """

    loss: FrequencyLoss
    target: WaveletBands
    fused_names: tuple[str, ...]
    level_terms: tuple[tuple[FrequencyTerm, float], ...]
    tensors: tuple[Tensor, ...]
    plan: fused.BandPlan | None = None
    l1_weights: Tensor | None = None

    @property
    def graph_key(self) -> Hashable:
        return id(self.plan), tuple(t.shape for t in self.tensors), self.fused_names

    def fused(self, pred: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
        """The fused terms of pred [B, C, H, W] against ``tensors`` (this stage's :attr:`tensors`, or a graph's
        copies of them), in :attr:`fused_names`' order."""
        if not self.fused_names or self.plan is None:
            return ()
        given = iter(tensors)
        slots = fused.SlotTarget(*(next(given) if name in self.fused_names else None for name in fused.OUTPUTS))
        c = self.loss.config
        kc_weight = c.kc_weight if "kc_loss" in self.fused_names else 0.0  # 0: computed level by level, if at all
        cbc_weight = c.cbc_weight if "cbc_loss" in self.fused_names else 0.0
        image = fused.as_planes(pred.to(_compute_dtype(pred.dtype)))
        outputs = fused.FusedFrequencyTerms.apply(image, self.plan, slots, self.l1_weights, kc_weight, cbc_weight)
        by_name = dict(zip(fused.OUTPUTS, outputs))
        return tuple(by_name[name] for name in self.fused_names)

    def level_by_level(self, pred: Tensor) -> dict[str, Tensor]:
        """The other active terms of pred [B, C, H, W]: one :meth:`FrequencyLoss.bands` with the statistics they read,
        then each term's function."""
        if not self.level_terms:
            return {}
        needs = {statistic for term, _ in self.level_terms for statistic in term.statistics}
        bands = self.loss.bands(pred, kurtosis="kurtosis" in needs, covariance="covariance" in needs,
                                check_finite=False)
        c = self.loss.config
        return {term.name: weight * term.function(bands, self.target, c) for term, weight in self.level_terms}

    def combine(self, fused_outputs: tuple[Tensor, ...] | list[Tensor], pred: Tensor) -> dict[str, Tensor]:
        """The fused terms' outputs (from :meth:`fused` or its graph) with the level-by-level terms of pred, in the
        table's order."""
        terms = dict(zip(self.fused_names, fused_outputs))
        terms.update(self.level_by_level(pred))
        return {term.name: terms[term.name] for term in TERMS if term.name in terms}

    def losses(self, pred: Tensor) -> dict[str, Tensor]:
        """Every active term of pred [B, C, H, W], by name, in the table's order."""
        return self.combine(self.fused(pred, *self.tensors), pred)


def target_key(batch: dict[str, Any], downscale: int, random_background: bool) -> tuple[int, int] | None:
    """Where a training loop caches a batch's ground-truth target (:meth:`FrequencyLoss.compare`'s ``key``): (the
    training image's index, the resolution's divisor) when the composited ground truth is the same at every visit
    (RGB, or RGBA over a fixed background), else None (RGBA over a ``random_background`` changes with every draw,
    and a batch without ``image_idx`` names no image). Our model and the nerfstudio plugin both key by it.

    >>> import torch
    >>> target_key({"image": torch.zeros(4, 4, 3), "image_idx": 2}, 4, random_background=True)
    (2, 4)
    >>> target_key({"image": torch.zeros(4, 4, 4), "image_idx": 2}, 4, random_background=True) is None
    True
    """
    fixed = batch["image"].shape[-1] == 3 or not random_background
    if not fixed or batch.get("image_idx") is None:
        return None
    return int(batch["image_idx"]), downscale


def _compute_dtype(dtype: torch.dtype) -> torch.dtype:
    """float32 for half precision (the detail coefficients' 4th powers need it, as in ``wavelets.dwt2``)."""
    return torch.float32 if dtype in (torch.float16, torch.bfloat16) else dtype
