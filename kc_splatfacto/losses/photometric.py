"""Pixel-space terms of the Splatfacto objective and the standard metrics; images are [B, C, H, W] in [0, 1].

- l1(pred, gt)    = mean |pred - gt|
- ssim(pred, gt)  = mean of kornia's SSIM map (Gaussian window 11, sigma 1.5, reflect 'same' padding, L = 1)
- dssim(pred, gt) = 1 - ssim: Splatfacto's D-SSIM term. NOT kornia.losses.ssim_loss, which is (1 - SSIM) / 2.
- psnr(pred, gt)  = 10 log10(max_val^2 / MSE), MSE over every element of the batch (torchmetrics' default).
"""

from __future__ import annotations

import torch
from torch import Tensor

SSIM_WINDOW = 11  # Splatfacto / 3DGS window


def _check_pair(pred: Tensor, gt: Tensor, min_size: int = 1) -> None:
    for name, x in (("pred", pred), ("gt", gt)):
        if not isinstance(x, Tensor) or x.dim() != 4:
            shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise ValueError(f"'{name}' must be an image batch [B, C, H, W], got {shape}")
    if pred.shape != gt.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} must have the same shape")
    if min(pred.shape[-2:]) < min_size:
        raise ValueError(f"images of size {tuple(pred.shape[-2:])} are too small: need at least {min_size} px per side")


def l1(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean absolute error (scalar)."""
    _check_pair(pred, gt)
    return (pred - gt).abs().mean()


def ssim(pred: Tensor, gt: Tensor, window_size: int = SSIM_WINDOW) -> Tensor:
    """Mean SSIM (scalar, 1 for identical images) via `kornia.metrics.ssim` (Gaussian sigma 1.5, data range 1)."""
    from kornia.metrics import ssim as kornia_ssim

    # reflect padding of window // 2 needs each side longer than that
    _check_pair(pred, gt, min_size=window_size // 2 + 1)
    return kornia_ssim(pred, gt, window_size, max_val=1.0).mean()


def dssim(pred: Tensor, gt: Tensor, window_size: int = SSIM_WINDOW) -> Tensor:
    """Splatfacto's D-SSIM term 1 - SSIM (scalar, in [0, 2])."""
    return 1.0 - ssim(pred, gt, window_size)


def psnr(pred: Tensor, gt: Tensor, max_val: float = 1.0) -> Tensor:
    """Peak signal-to-noise ratio in dB (scalar; +inf for identical images)."""
    _check_pair(pred, gt)
    mse = (pred.detach().float() - gt.detach().float()).square().mean()
    return 10.0 * torch.log10(max_val**2 / mse)
