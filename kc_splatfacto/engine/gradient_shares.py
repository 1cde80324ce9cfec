"""Gradient shares: how hard each loss term pulls on the render, relative to the photometric term.

For each term L_t of a step's loss dict and the rendered image I (the tensor the losses were computed from)::

    norm_t  = || dL_t / dI ||_2                       (over every pixel and channel)
    share_t = norm_t / norm_ref                       ref = the photometric term ``main_loss``
    top_t   = sum of ||dL_t/dI(p)||^2 over the top ``top_fraction`` of pixels p / norm_t^2

``share_t`` says whether a term does anything next to the photometric term at its weight (a share of 0.001 is a term
that only costs time); ``top_t`` says whether its pull is spread over the image or concentrated in a few pixels.
Terms without a path to the image (e.g. ``scale_reg``) have no image gradient and are left out.

Only the loss graph is differentiated (``torch.autograd.grad`` w.r.t. the image, graph retained), never the
rasterizer, so the step's own backward and density-control statistics are untouched; about 60 ms per
logged step for the four terms of a 192x128 render on the 2-core CPU here (once every 100 steps by default).
Optionally, for a one-off measurement, also w.r.t. other tensors such as the means (``wrt``): that runs the
rasterizer's backward once per term and would add to ``means2d.absgrad``, so the trainer never asks for it.
"""

from __future__ import annotations

import math
from typing import Mapping

import torch

REFERENCE_TERM = "main_loss"
"""the photometric term every share is relative to: (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM)"""
TOP_FRACTION = 0.01
"""fraction of pixels whose share of the squared gradient norm is reported (``top``)"""


def _pixel_energy(grad: torch.Tensor) -> torch.Tensor:
    """[H, W, C] (or [B, C, H, W]) gradient -> [P] squared norm per pixel (summed over channels)."""
    if grad.ndim == 3:  # [H, W, C], the model's render layout
        return (grad.double() ** 2).sum(-1).reshape(-1)
    if grad.ndim == 4:  # [B, C, H, W]
        return (grad.double() ** 2).sum(1).reshape(-1)
    return (grad.double() ** 2).reshape(-1)


def top_pixel_fraction(grad: torch.Tensor, fraction: float = TOP_FRACTION) -> float:
    """Fraction of ||grad||^2 carried by the top ``fraction`` of pixels (at least one pixel); NaN for a zero grad."""
    energy = _pixel_energy(grad)
    total = float(energy.sum())
    if total == 0.0:
        return math.nan
    k = max(1, int(math.ceil(fraction * energy.numel())))
    return float(torch.topk(energy, k).values.sum()) / total


def gradient_shares(
    loss_dict: Mapping[str, torch.Tensor],
    image: torch.Tensor,
    *,
    reference: str = REFERENCE_TERM,
    top_fraction: float = TOP_FRACTION,
    wrt: Mapping[str, torch.Tensor] | None = None,
) -> dict[str, dict[str, float]]:
    """Per-term gradient norms w.r.t. ``image`` (and optionally ``wrt`` tensors), relative to ``reference``'s.

    Args:
        loss_dict: scalar loss terms (already weighted), all computed from ``image`` in one graph.
        image: the render, e.g. [H, W, 3]; must be part of the terms' graph (not detached).
        reference: the term shares are relative to (must be in ``loss_dict`` and reach ``image``).
        top_fraction: pixel fraction for ``top``.
        wrt: optional {name: tensor} (e.g. ``{"means": model.means}``) for extra norms and shares.
    Returns:
        ``{"norm": {term: float}, "share": {term: float}, "top": {term: float}}``, plus
        ``"norm_<name>"`` / ``"share_<name>"`` for each ``wrt`` name. A term's share is NaN when the reference's
        gradient is zero. The graph is retained, so the caller can still call ``backward``.
    """
    if reference not in loss_dict:
        raise KeyError(f"gradient_shares: reference term '{reference}' not in the loss dict ({list(loss_dict)})")
    if not image.requires_grad:
        raise ValueError("gradient_shares: the image does not require grad (pass the render the losses were computed from)")
    targets = {"": image, **{f"_{name}": tensor for name, tensor in (wrt or {}).items()}}
    out: dict[str, dict[str, float]] = {"norm": {}, "share": {}, "top": {}}
    for suffix in targets:
        if suffix:
            out[f"norm{suffix}"], out[f"share{suffix}"] = {}, {}
    for term, value in loss_dict.items():
        if not value.requires_grad:
            continue
        grads = torch.autograd.grad(value, list(targets.values()), retain_graph=True, allow_unused=True)
        for (suffix, _), grad in zip(targets.items(), grads):
            if grad is None:
                continue
            out[f"norm{suffix}"][term] = float(torch.linalg.vector_norm(grad.double()))
            if not suffix:
                out["top"][term] = top_pixel_fraction(grad, top_fraction)
    for suffix in targets:
        norms = out[f"norm{suffix}"]
        if reference not in norms:
            if not suffix:
                raise ValueError(f"gradient_shares: the reference term '{reference}' does not depend on the image")
            continue
        ref = norms[reference]
        out[f"share{suffix}"] = {term: (n / ref if ref > 0 else math.nan) for term, n in norms.items()}
    return out
