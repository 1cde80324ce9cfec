"""Pixel-space terms of the Splatfacto objective; images are [B, C, H, W] in [0, 1].

- l1(pred, gt)    = mean |pred - gt|
- dssim(pred, gt) = 1 - mean SSIM (:func:`kc_splatfacto.metrics.mean_ssim`): Splatfacto's D-SSIM term. NOT
                    kornia.losses.ssim_loss, which is (1 - SSIM) / 2.

The metrics themselves (PSNR, the SSIM map and its mean) are in :mod:`kc_splatfacto.metrics`.
"""

from __future__ import annotations

from torch import Tensor

from kc_splatfacto.metrics import SSIM_WINDOW, _check_pair, mean_ssim


def l1(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean absolute error (scalar)."""
    _check_pair(pred, gt)
    # gt first: the difference takes gt's memory layout (the reduction order, hence the last bits, follow it)
    return (gt - pred).abs().mean()


def dssim(pred: Tensor, gt: Tensor, window_size: int = SSIM_WINDOW) -> Tensor:
    """Splatfacto's D-SSIM term 1 - SSIM (scalar, in [0, 2])."""
    return 1.0 - mean_ssim(pred, gt, window_size)
