"""Image-quality metrics (kornia's names and meanings); images are [B, C, H, W] in [0, max_val].

- psnr(pred, gt, mask)      = 10 log10(max_val^2 / MSE), the MSE over every element of the batch (torchmetrics'
                              default), or over the pixels where ``mask`` is set
- ssim(pred, gt)            = kornia's SSIM *map* [B, C, H, W] (Gaussian window 11, sigma 1.5, reflect 'same'
                              padding, C1 = (0.01 L)^2, C2 = (0.03 L)^2)
- mean_ssim(pred, gt, mask) = the map's mean (over the pixels where ``mask`` is set): the number reported as "SSIM"
- lpips(pred, gt, net)      = LPIPS v0.1 ("alex" or "vgg"), images in [0, 1] (see :mod:`kc_splatfacto.lpips`)

A mask is [B, 1, H, W] (bool or {0, 1} float), True/1 = the pixel counts. Masked metrics are computed on the images
the masked losses compare (pred and gt both multiplied by the mask, see ``SplatfactoModel.get_loss_dict``); the
mean then runs over the counted pixels only, so a masked-out region neither helps nor hurts a score.
"""

from __future__ import annotations

import torch
from torch import Tensor

from kc_splatfacto.lpips import lpips

SSIM_WINDOW = 11
"""Splatfacto / 3DGS window"""
SSIM_SIGMA = 1.5
"""the Gaussian window's standard deviation (kornia's SSIM, as in Wang et al. 2004)"""
SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
"""SSIM's stabilising constants (k1 L)^2 and (k2 L)^2 for the dynamic range L = 1 (kornia's)"""
SSIM_EPS = 1e-12
"""added to the SSIM denominator (kornia's default eps)"""


def _check_pair(pred: Tensor, gt: Tensor, min_size: int = 1) -> None:
    for name, x in (("pred", pred), ("gt", gt)):
        if not isinstance(x, Tensor) or x.dim() != 4:
            shape = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
            raise ValueError(f"'{name}' must be an image batch [B, C, H, W], got {shape}")
    if pred.shape != gt.shape:
        raise ValueError(f"pred {tuple(pred.shape)} and gt {tuple(gt.shape)} must have the same shape")
    if min(pred.shape[-2:]) < min_size:
        raise ValueError(f"images of size {tuple(pred.shape[-2:])} are too small: need at least {min_size} px per side")


def _check_mask(mask: Tensor, like: Tensor) -> Tensor:
    """[B, 1, H, W] mask as float; raises when it does not fit ``like`` [B, C, H, W] or selects nothing."""
    if not isinstance(mask, Tensor) or mask.dim() != 4 or mask.shape[1] != 1 or mask.shape[0] != like.shape[0] \
            or mask.shape[-2:] != like.shape[-2:]:
        shape = tuple(mask.shape) if isinstance(mask, Tensor) else type(mask).__name__
        raise ValueError(f"mask must be [B, 1, H, W] = [{like.shape[0]}, 1, {like.shape[2]}, {like.shape[3]}], got {shape}")
    mask = mask.to(like.dtype)
    if not bool((mask.sum() > 0).item()):
        raise ValueError("the mask selects no pixel: nothing to compare")
    return mask


def _masked_mean(values: Tensor, mask: Tensor | None) -> Tensor:
    """Mean of [B, C, H, W] values, over the pixels (all channels) where the [B, 1, H, W] mask is set."""
    if mask is None:
        return values.mean()
    return (values * mask).sum() / (mask.sum() * values.shape[1])


def psnr(pred: Tensor, gt: Tensor, max_val: float = 1.0, mask: Tensor | None = None) -> Tensor:
    """Peak signal-to-noise ratio in dB (scalar; +inf for identical images). No gradient (a metric).

    Args:
        pred, gt: [B, C, H, W].
        mask: optional [B, 1, H, W]; the MSE runs over the pixels where it is set.
    """
    _check_pair(pred, gt)
    if mask is not None:
        mask = _check_mask(mask, pred).float()
    mse = _masked_mean((pred.detach().float() - gt.detach().float()).square(), mask)
    return 10.0 * torch.log10(max_val**2 / mse)


def ssim(pred: Tensor, gt: Tensor, window_size: int = SSIM_WINDOW, max_val: float = 1.0) -> Tensor:
    """SSIM map [B, C, H, W] (1 where the images agree) via ``kornia.metrics.ssim``; differentiable."""
    from kornia.metrics import ssim as kornia_ssim

    # reflect padding of window // 2 needs each side longer than that
    _check_pair(pred, gt, min_size=window_size // 2 + 1)
    return kornia_ssim(pred, gt, window_size, max_val=max_val)


def mean_ssim(
    pred: Tensor, gt: Tensor, window_size: int = SSIM_WINDOW, max_val: float = 1.0, mask: Tensor | None = None
) -> Tensor:
    """Mean of the :func:`ssim` map (scalar, 1 for identical images), over the pixels where ``mask`` is set."""
    if mask is not None:
        mask = _check_mask(mask, pred)
    return _masked_mean(ssim(pred, gt, window_size, max_val), mask)


__all__ = ["lpips", "mean_ssim", "psnr", "ssim"]
