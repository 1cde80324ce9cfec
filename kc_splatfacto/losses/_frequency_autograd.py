"""The frequency losses' passes over the subbands and their hand-written backwards: the plumbing under the formulas
of :mod:`kc_splatfacto.losses.frequency`.

Each pass comes twice, as a torch autograd Function for any device and as one over the compiled CPU kernels
(``_dwt_kernels``: float64 sums, one call each way); :func:`level_moments` and :func:`weighted_band_l1` choose by the
tensor's device (``backend.compiled``), so the formulas above never see the difference.

- :func:`level_moments`: per level, m2 = mean z^2, m4 = mean z^4 and cov = z z^T / (P - 1) of the centred,
  RMS-normalized subbands z = (x - mean(x)) / s, s^2 the image's mean coefficient power (detached). Backward:
  dz = z (2 g2 + 4 g4 z^2) / P + (G + G^T) z / (P - 1), then dx = (dz - mean(dz)) / s (~5 torch passes over the band
  where autograd through the elementwise chain takes ~12).
- :func:`weighted_band_l1`: sum_j w_j mean|pred_j - gt_j| over the levels' detail bands; its backward is
  w_j sign(pred_j - gt_j) / count_j, 0 where equal (torch's ``l1_loss``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from kc_splatfacto import backend
from kc_splatfacto.losses.wavelets import WaveletCoeffs

POWER_FLOOR = 1e-30
"""floor of the image power s^2, only active for an all-zero image (then every band is 0 and s only has to be > 0)"""

Moments = tuple[Tensor, Tensor | None, Tensor | None]
"""one level's (m2 [B, C, 3], m4 [B, C, 3] or None, cov [B, C, 3, 3] or None)"""


# --------------------------------------------------------------------------------------------------- image power


def _image_power(coeffs: WaveletCoeffs) -> Tensor:
    """[B, C, 1] mean square over all the image's coefficients (approx and details), detached, floored."""
    with torch.no_grad():
        # one joined copy and one dot product, not two passes per band tensor: on a GPU, where the step is bound by
        # kernel launches, 8 fewer ops a forward (counted on the CPU, tests/losses/test_frequency_launches.py)
        flat = torch.cat([coeffs.approx.flatten(-2), *(band.flatten(-3) for band in coeffs.details)], dim=-1)
        return (torch.linalg.vecdot(flat, flat) / flat.shape[-1]).clamp_min(POWER_FLOOR).unsqueeze(-1)


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


# --------------------------------------------------------------------------------------------------- band moments


class _CentredMoments(torch.autograd.Function):
    """Moments of one level's centred, RMS-normalized subbands, torch ops (any device).

    x [..., 3, P], inv_rms [..., 1, 1] -> m2 [..., 3], m4 [..., 3] (if wanted), cov [..., 3, 3] (if wanted).
    """

    @staticmethod
    def forward(ctx, flat: Tensor, inv_rms: Tensor, want_m4: bool, want_cov: bool):
        count = flat.shape[-1]
        # few ops, not few passes: on a GPU the step is bound by kernel launches (each op one)
        z = (flat - flat.mean(dim=-1, keepdim=True)) * inv_rms  # (x - mean) / s
        z2 = z.square()
        m2 = z2.mean(dim=-1)
        m4 = cov = None
        if want_m4:
            m4 = z2.square().mean(dim=-1)
        if want_cov:
            cov = torch.matmul(z, z.transpose(-1, -2)) / max(count - 1, 1)  # numpy.cov's (P - 1) normalization
        ctx.save_for_backward(z, z2 if want_m4 else None, inv_rms)  # z2 saves the backward two passes
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


class _CentredMomentsCPU(torch.autograd.Function):
    """:class:`_CentredMoments` as one compiled call each way (``_dwt_kernels.band_moments`` and its adjoint, parallel
    over pixel chunks, float64 sums); ``inv_rms`` comes in float64."""

    @staticmethod
    def forward(ctx, flat: Tensor, inv_rms: Tensor, want_m4: bool, want_cov: bool):
        from kc_splatfacto.losses._dwt_kernels import N_DETAIL_BANDS, band_moments

        lead = flat.shape[:-2]
        bands = flat.detach().reshape(-1, N_DETAIL_BANDS, flat.shape[-1]).contiguous()
        planes = bands.shape[0]
        means, m2, m4 = (np.zeros((planes, N_DETAIL_BANDS)) for _ in range(3))
        cross = np.zeros((planes, N_DETAIL_BANDS, N_DETAIL_BANDS))
        scale = inv_rms.detach().to(torch.float64).reshape(planes).contiguous().numpy()
        band_moments(bands.numpy(), scale, want_m4, want_cov, means, m2, m4, cross)
        ctx.save_for_backward(bands)
        ctx.means, ctx.scale, ctx.flat_shape = means, scale, flat.shape

        def as_output(moment: np.ndarray) -> Tensor:
            return torch.from_numpy(moment).to(flat.dtype).reshape(*lead, *moment.shape[1:])

        return as_output(m2), as_output(m4) if want_m4 else None, as_output(cross) if want_cov else None

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_m2: Tensor | None, grad_m4: Tensor | None, grad_cov: Tensor | None):
        from kc_splatfacto.losses._dwt_kernels import N_DETAIL_BANDS, band_moments_adjoint

        (bands,) = ctx.saved_tensors
        means, scale = ctx.means, ctx.scale
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
        return grad.reshape(ctx.flat_shape), None, None, None


def level_moments(coeffs: WaveletCoeffs, want_m4: bool, want_cov: bool) -> tuple[list[Moments], Tensor]:
    """Per level (finest first) the moments of the RMS-normalized centred subbands (see the module docstring), and
    the image power s^2 [B, C, 1] they are normalized by."""
    if backend.compiled(coeffs.approx):
        power64 = _image_power_cpu(coeffs)
        power = power64.to(coeffs.approx.dtype)
        inv_rms = torch.rsqrt(power64).unsqueeze(-1)  # [B, C, 1, 1] float64: the compiled pass's scale
        moments_of = _CentredMomentsCPU.apply
    else:
        power = _image_power(coeffs)
        inv_rms = torch.rsqrt(power).unsqueeze(-1)  # [B, C, 1, 1]
        moments_of = _CentredMoments.apply
    moments = [moments_of(band.flatten(-2), inv_rms, want_m4, want_cov) for band in coeffs.details]
    return moments, power


# --------------------------------------------------------------------------------------------------- weighted L1


class _WeightedBandL1CPU(torch.autograd.Function):
    """:func:`weighted_band_l1` on CPU, one compiled pass per level each way (float64 sums)."""

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


def weighted_band_l1(weights: list[float], preds: Sequence[Tensor], targets: Sequence[Tensor]) -> Tensor:
    """sum_j weights[j] mean|preds[j] - targets[j]| (scalar), the targets detached."""
    if backend.compiled(preds[0]):
        return _WeightedBandL1CPU.apply(weights, [band.detach() for band in targets], *preds)
    loss = preds[0].new_zeros(())
    for weight, band_pred, band_gt in zip(weights, preds, targets):
        loss = loss + weight * F.l1_loss(band_pred, band_gt.detach())
    return loss
