"""Loss layer: differentiable DWT, frequency-domain losses (wavelet L1, KC, CBC) and photometric losses.

Metrics (PSNR, SSIM) are in :mod:`kc_splatfacto.metrics`."""

from kc_splatfacto.losses.frequency import (
    WEIGHTINGS,
    FrequencyLoss,
    FrequencyLossConfig,
    WaveletBands,
    band_kurtosis,
    cbc_loss,
    covariance_penalty,
    cross_band_covariance,
    diagonal_sparsity,
    kc_loss,
    kurtosis_spread,
    level_weights,
    lowpass_l1,
    mean_band_kurtosis,
    prepare_target,
    wavelet_bands,
    wavelet_l1,
)
from kc_splatfacto.losses.photometric import dssim, l1
from kc_splatfacto.losses.wavelets import MODES, WaveletCoeffs, daubechies_filters, dwt2, dwt_max_level

__all__ = [
    "MODES",
    "WEIGHTINGS",
    "FrequencyLoss",
    "FrequencyLossConfig",
    "WaveletCoeffs",
    "WaveletBands",
    "band_kurtosis",
    "cbc_loss",
    "covariance_penalty",
    "cross_band_covariance",
    "diagonal_sparsity",
    "daubechies_filters",
    "dssim",
    "dwt2",
    "dwt_max_level",
    "kc_loss",
    "kurtosis_spread",
    "l1",
    "level_weights",
    "lowpass_l1",
    "mean_band_kurtosis",
    "prepare_target",
    "wavelet_bands",
    "wavelet_l1",
]
