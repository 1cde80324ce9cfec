"""Pixel-space terms of the Splatfacto objective; images are [B, C, H, W] in [0, 1].

- l1(pred, gt)    = mean |pred - gt|
- dssim(pred, gt) = 1 - mean SSIM (:func:`kc_splatfacto.metrics.mean_ssim`): Splatfacto's D-SSIM term. NOT
                    kornia.losses.ssim_loss, which is (1 - SSIM) / 2.

On the CPU (``kc_splatfacto.backend``) the D-SSIM of a prediction against a fixed image runs fused (``losses/_ssim_kernels.py``: the five moments'
separable blur, the map and its mean in one pass, an analytic backward through the blur's adjoint): kornia's SSIM
with autograd took ~15 ms of a 50 ms training step at 192x128 (oneDNN copies every depthwise convolution's image into
blocked layout), the fused one ~1 ms. Same formula, window and padding; it agrees with kornia to float rounding
(tests/losses/test_photometric.py). kornia stays the evaluation metric and the oracle.

The metrics themselves (PSNR, the SSIM map and its mean) are in :mod:`kc_splatfacto.metrics`.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from kc_splatfacto import backend
from kc_splatfacto.metrics import SSIM_C1, SSIM_C2, SSIM_EPS, SSIM_SIGMA, SSIM_WINDOW, _check_pair, mean_ssim


def l1(pred: Tensor, gt: Tensor) -> Tensor:
    """Mean absolute error (scalar)."""
    _check_pair(pred, gt)
    # gt first: the difference takes gt's memory layout (the reduction order, hence the last bits, follow it)
    return (gt - pred).abs().mean()


def dssim(pred: Tensor, gt: Tensor, window_size: int = SSIM_WINDOW) -> Tensor:
    """Splatfacto's D-SSIM term 1 - SSIM (scalar, in [0, 2]); pred, gt [B, C, H, W].

    Fused on the CPU (float32 / float64, ``gt`` without gradient, an odd window); kornia's SSIM otherwise.
    """
    _check_pair(pred, gt, min_size=window_size // 2 + 1)
    if _fused_eligible(pred, gt, window_size):
        return _FusedDSSIM.apply(pred, gt, window_size)
    return 1.0 - mean_ssim(pred, gt, window_size)


def _fused_eligible(pred: Tensor, gt: Tensor, window_size: int) -> bool:
    return (backend.compiled(pred, gt) and pred.dtype in (torch.float32, torch.float64)
            and gt.dtype == pred.dtype and not gt.requires_grad and window_size % 2 == 1)


@functools.cache
def _gaussian_taps(window_size: int, dtype: torch.dtype) -> np.ndarray:
    """kornia's normalised 1D Gaussian window [K] (the very taps its SSIM uses), as read-only numpy (built once:
    kornia's construction costs about as much as the fused forward itself)."""
    from kornia.filters import get_gaussian_kernel1d

    taps = get_gaussian_kernel1d(window_size, SSIM_SIGMA, dtype=dtype).reshape(-1).contiguous().numpy().copy()
    taps.setflags(write=False)
    return taps


class _FusedDSSIM(torch.autograd.Function):
    """1 - mean SSIM map of (pred, gt) with the gradient w.r.t. pred only (``_ssim_kernels`` says how)."""

    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor, window_size: int) -> Tensor:
        from . import _ssim_kernels as SK

        batch, channels, height, width = pred.shape
        planes = batch * channels
        x = np.ascontiguousarray(pred.detach().numpy()).reshape(planes, height, width)
        y = np.ascontiguousarray(gt.detach().numpy()).reshape(planes, height, width)
        taps = _gaussian_taps(window_size, pred.dtype)
        scalar = x.dtype.type
        stacked = np.empty((SK.N_MOMENTS * planes, height, width), x.dtype)
        SK.stack_moments_input(x, y, stacked.reshape(SK.N_MOMENTS, planes, height, width))
        blurred_rows = np.empty_like(stacked)
        SK.blur_rows(stacked, taps, blurred_rows)
        moments = stacked  # reused: the stacked images are not needed any more
        SK.blur_cols(blurred_rows, taps, moments)
        row_sums = np.empty(planes * height, np.float64)
        partials = np.empty((SK.N_PARTIALS, planes, height, width), x.dtype)
        SK.ssim_partials(moments.reshape(SK.N_MOMENTS, planes, height, width), scalar(SSIM_C1), scalar(SSIM_C2),
                         scalar(SSIM_EPS), row_sums, partials)
        ctx.arrays = (x, y, taps, partials)
        ctx.shape = tuple(pred.shape)
        mean = float(row_sums.sum()) / (planes * height * width)  # numpy's fixed pairwise order
        return torch.tensor(1.0 - mean, dtype=pred.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor):
        from . import _ssim_kernels as SK

        x, y, taps, partials = ctx.arrays
        planes, height, width = x.shape
        flat = partials.reshape(SK.N_PARTIALS * planes, height, width)
        cols_adjoint = np.empty_like(flat)
        SK.blur_cols_adjoint(flat, taps, cols_adjoint)
        blurred = np.empty_like(flat)
        SK.blur_rows_adjoint(cols_adjoint, taps, blurred)
        v_pred = np.empty_like(x)
        # d(1 - mean s)/ds = -1 / N at every pixel
        scale = x.dtype.type(-float(grad_out.numpy()) / x.size)  # the CPU kernels' scalar, read as their arrays are
        SK.ssim_input_grad(blurred.reshape(SK.N_PARTIALS, planes, height, width), x, y, scale, v_pred)
        return torch.from_numpy(v_pred).reshape(ctx.shape), None, None
