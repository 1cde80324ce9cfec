"""Pixel-space terms of the Splatfacto objective; images are [B, C, H, W] in [0, 1].

- l1(pred, gt)    = mean |pred - gt|
- dssim(pred, gt) = 1 - mean SSIM (:func:`kc_splatfacto.metrics.mean_ssim`): Splatfacto's D-SSIM term. NOT
                    kornia.losses.ssim_loss, which is (1 - SSIM) / 2.

On the CPU (``kc_splatfacto.backend``) the D-SSIM of a prediction against a fixed image runs fused (``losses/_ssim_kernels.py``: the five moments'
separable blur, the map and its mean in one pass, an analytic backward through the blur's adjoint): kornia's SSIM
with autograd took ~15 ms of a 50 ms training step at 192x128 (oneDNN copies every depthwise convolution's image into
blocked layout), the fused one ~1 ms. Same formula, window and padding; it agrees with kornia to float rounding
(tests/losses/test_photometric.py). kornia stays the evaluation metric and the oracle.

Elsewhere (a GPU, where a step is bound by kernel launches) the same D-SSIM is one autograd Function of ~40 tensor
operations forward and backward, where kornia's SSIM under autograd takes ~120: the five moments stacked and blurred
by one grouped convolution after one reflect padding, the map's formula on the stacked moments, and the backward
written out as on the CPU (the map's partials, the blur's adjoint as one transposed convolution and the padding's
adjoint).

The metrics themselves (PSNR, the SSIM map and its mean) are in :mod:`kc_splatfacto.metrics`.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
import torch.nn.functional as F
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
    if _stacked_eligible(pred, gt, window_size):
        return _StackedDSSIM.apply(pred, gt, window_size)
    return 1.0 - mean_ssim(pred, gt, window_size)


def _stacked_eligible(pred: Tensor, gt: Tensor, window_size: int) -> bool:
    return (pred.dtype in (torch.float32, torch.float64) and gt.dtype == pred.dtype and not gt.requires_grad
            and window_size % 2 == 1 and pred.device == gt.device)


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


@functools.lru_cache(maxsize=8)
def _window(window_size: int, planes: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """kornia's 2D Gaussian window as grouped-convolution weights for ``planes`` images: [planes, 1, K, K]."""
    taps = torch.tensor(_gaussian_taps(window_size, torch.float64), device=device)  # a copy: the taps are read-only
    return torch.outer(taps, taps).to(dtype).expand(planes, 1, window_size, window_size).contiguous()


@functools.lru_cache(maxsize=8)
def _ssim_constants(dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """(c [2, 1, 1, 1] = (C1, C2), eps, the partials' factors [3, 1, 1, 1] = (2, 1, 2), the mu index pair)."""
    c = torch.tensor([SSIM_C1, SSIM_C2], dtype=dtype, device=device).reshape(2, 1, 1, 1)
    eps = torch.tensor(SSIM_EPS, dtype=dtype, device=device)
    factors = torch.tensor([2.0, 1.0, 2.0], dtype=dtype, device=device).reshape(3, 1, 1, 1)
    pairs = torch.tensor([[0, 1, 0], [0, 1, 1]], device=device)
    return c, eps, factors, pairs


class _StackedDSSIM(torch.autograd.Function):
    """1 - mean SSIM map of (pred, gt), gradient w.r.t. pred only, in few tensor operations (module docstring).

    Moments M = blur([x, y, x^2, y^2, xy]) [5, P, H, W]; with (mu_x^2, mu_y^2, mu_x mu_y) and the (co)variances,
    A = 2 mu_x mu_y + C1, B = 2 s_xy + C2, Cd = mu_x^2 + mu_y^2 + C1, D = s_x^2 + s_y^2 + C2, the map is
    A B / (Cd D + eps), kornia's, whose partials w.r.t. (mu_x, E[x^2], E[xy]) are those of ``_ssim_kernels``.
    """

    @staticmethod
    def forward(ctx, pred: Tensor, gt: Tensor, window_size: int) -> Tensor:
        batch, channels, height, width = pred.shape
        planes = batch * channels
        x, y = pred.reshape(planes, height, width), gt.reshape(planes, height, width)
        c, eps, _, pairs = _ssim_constants(pred.dtype, pred.device)
        weights = _window(window_size, 5 * planes, pred.dtype, pred.device)
        pad = window_size // 2
        stacked = torch.stack([x, y, x * x, y * y, x * y]).view(1, 5 * planes, height, width)
        moments = F.conv2d(F.pad(stacked, (pad, pad, pad, pad), mode="reflect"), weights, groups=5 * planes)
        moments = moments.view(5, planes, height, width)
        mu = moments[:2]
        squares = torch.empty((2, 3, planes, height, width), dtype=pred.dtype, device=pred.device)
        torch.mul(mu.index_select(0, pairs[0]), mu.index_select(0, pairs[1]), out=squares[0])  # mu_x^2, mu_y^2, mu_xy
        torch.sub(moments[2:], squares[0], out=squares[1])  # s_x^2, s_y^2, s_xy
        numerator = torch.add(c, squares[:, 2], alpha=2.0)  # (A, B)
        denominator = (squares[:, 0] + squares[:, 1]).add_(c)  # (Cd, D)
        den = torch.addcmul(eps, denominator[0], denominator[1])
        value = (numerator[0] * numerator[1]).div_(den)
        ctx.save_for_backward(x, y, mu, numerator, denominator, den, value)
        ctx.window = (window_size, planes)
        ctx.shape = pred.shape
        return 1.0 - value.mean()

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out: Tensor):
        x, y, mu, numerator, denominator, den, value = ctx.saved_tensors
        window_size, planes = ctx.window
        _, _, factors, _ = _ssim_constants(x.dtype, x.device)
        inv_den = den.reciprocal()
        d_ab = numerator.flip(0).mul_(inv_den)  # (d/dA, d/dB) = (B, A) / den
        d_cd = denominator.flip(0).mul_((value * inv_den).neg_())  # (d/dCd, d/dD) = -value (D, Cd) / den
        # through mu_x (A: 2 mu_y, B: -2 mu_y, Cd: 2 mu_x, D: -2 mu_x), E[x^2] (D: 1) and E[xy] (B: 2)
        g_mu = torch.mul(mu[1], d_ab[0] - d_ab[1]).addcmul_(mu[0], d_cd[0] - d_cd[1])
        partials = torch.stack([g_mu, d_cd[1], d_ab[1]]).mul_(factors * (-grad_out / x.numel()))
        height, width = x.shape[-2:]
        pad = window_size // 2
        weights = _window(window_size, 3 * planes, x.dtype, x.device)
        # the blur's adjoint: a transposed convolution onto the padded image, then the reflect padding's adjoint
        spread = F.conv_transpose2d(partials.view(1, 3 * planes, height, width), weights, groups=3 * planes)
        folded = torch.ops.aten.reflection_pad2d_backward(spread, spread.new_empty((1, 3 * planes, height, width)),
                                                          [pad, pad, pad, pad]).view(3, planes, height, width)
        grad = torch.addcmul(folded[0], x, folded[1], value=2.0).addcmul_(y, folded[2])
        return grad.view(ctx.shape), None, None
