"""The image-space loss of a training render: Splatfacto's main loss and KC-3DGS's frequency terms as one region,
replayed as a CUDA graph per image size on a GPU.

On CUDA a training step is bound by kernel launches, and this region (L1, D-SSIM, the DWT, the band statistics and
their backwards) is ~150 of them. :class:`ImageLoss` captures it once per training resolution with
``torch.cuda.make_graphed_callables`` and replays it: a copy of the inputs and one graph launch each way. What the
graph reads is passed in as tensors (the render, the ground truth, the ground truth's cached wavelet target), so one
graph serves every training image of a size. The first replay of each size is checked against the eager
computation, values and gradient; a failed capture or a mismatch turns the graphs off for the run with one warning,
and the eager loss goes on. Elsewhere (the CPU) the loss is always eager.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Hashable
from typing import Any

import torch
from torch import Tensor

from kc_splatfacto.losses import _fused_frequency as fused
from kc_splatfacto.losses.frequency import FrequencyLoss
from kc_splatfacto.losses.layout import channels_first
from kc_splatfacto.losses.photometric import dssim, l1

GRAPH_CHECK_RTOL = 1e-4
"""how close a graph's first replay must come to the eager loss (values, and the gradient relative to its peak)"""

Capture = Callable[[Callable[..., Any], tuple[Tensor, ...]], Callable[..., Any]]
"""(region, sample inputs) -> the replayable region (``torch.cuda.make_graphed_callables``'s shape)"""


def _make_graphed(region: Callable[..., Any], sample: tuple[Tensor, ...]) -> Callable[..., Any]:
    return torch.cuda.make_graphed_callables(region, sample, num_warmup_iters=3)


class ImageLoss:
    """``main_loss`` = (1 - ssim_lambda) L1 + ssim_lambda (1 - SSIM), and the frequency loss's active terms (already
    weighted), of a render against its ground truth, both [h, w, 3] (composited and masked by the caller).

    Args:
        ssim_lambda: the D-SSIM weight of the main loss.
        frequency_loss: KC-3DGS's terms, or None (Splatfacto).
        cuda_graphs: capture the region as CUDA graphs on a GPU (see the module docstring).
        capture: how a region is captured (tests replace it; the default is ``torch.cuda.make_graphed_callables``).
    """

    def __init__(self, ssim_lambda: float, frequency_loss: FrequencyLoss | None, cuda_graphs: bool = True,
                 capture: Capture = _make_graphed) -> None:
        self.ssim_lambda = float(ssim_lambda)
        self.frequency_loss = frequency_loss
        self.cuda_graphs = cuda_graphs
        self._capture = capture
        self._graphs: dict[Hashable, Callable[..., Any]] = {}
        self._checked: set[Hashable] = set()

    def __call__(self, render: Tensor, gt: Tensor, key: Hashable | None = None) -> dict[str, Tensor]:
        """The loss terms by name; ``key`` identifies the ground truth for the frequency loss's target cache (None:
        not cached)."""
        if self.cuda_graphs and self._graphs_apply(render, gt):
            losses = self._graphed(render, gt, key)
            if losses is not None:
                return losses
        return self.eager(render, gt, key)

    def eager(self, render: Tensor, gt: Tensor, key: Hashable | None = None) -> dict[str, Tensor]:
        """The loss terms computed op by op (the CPU's path, and the graphs' reference)."""
        pred, target = channels_first(render), channels_first(gt)
        lam = self.ssim_lambda
        losses = {"main_loss": (1 - lam) * l1(pred, target) + lam * dssim(pred, target)}
        if self.frequency_loss is not None:
            # the same view of the render as the main loss's: the gradients of all terms meet in one node, summed in
            # one order (a second view would sum them in another: other float rounding, another whole-run hash)
            losses.update(self.frequency_loss(pred, self.frequency_loss.target(target, key)))
        return losses

    # ----------------------------------------------------------------------------------------------- graphs
    def _graphs_apply(self, render: Tensor, gt: Tensor) -> bool:
        return (render.device.type == "cuda" and render.requires_grad and render.dtype == torch.float32
                and gt.dtype == render.dtype and torch.is_grad_enabled())

    def _graphed(self, render: Tensor, gt: Tensor, key: Hashable | None) -> dict[str, Tensor] | None:
        """The terms through the size's graph (captured and checked on first use), or None where the eager path
        must serve (the frequency loss off its fused path, an image too small for a DWT level, graphs turned off)."""
        frequency = self.frequency_loss
        names = ["main_loss"]
        plan: fused.BandPlan | None = None
        weights: Tensor | None = None
        present: list[bool] = []  # which of the slot target's tensors (weighted bands, kurtosis, L_cov) exist
        slot_tensors: tuple[Tensor, ...] = ()
        if frequency is not None:
            if not frequency.takes_fused_path(channels_first(render)):
                return None
            prepared = frequency.fused_target(render.detach().permute(2, 0, 1),
                                              frequency.target(channels_first(gt), key))
            if prepared is None:
                return None
            plan, slots, weights = prepared
            fields = (slots.weighted_bands, slots.kurtosis, slots.l_cov)
            present = [t is not None for t in fields]
            slot_tensors = tuple(t for t in fields if t is not None)
            names += [term.name for term, _ in frequency.config.active_terms()]
        graph_key = (tuple(render.shape), id(plan), tuple(t.shape for t in slot_tensors))
        graph = self._graphs.get(graph_key)
        if graph is None:
            region = self._region(plan, weights, present)
            sample = (render.detach().clone().requires_grad_(True), gt.detach().clone(),
                      *(t.clone() for t in slot_tensors))
            try:
                graph = self._graphs[graph_key] = self._capture(region, sample)
            except Exception as error:  # noqa: BLE001  (any failure to capture leaves the eager loss in charge)
                self._turn_off(f"capturing the image loss at {tuple(render.shape[:2])} failed ({error})")
                return None
        if graph_key not in self._checked and not self._agrees_with_eager(graph, render, gt, key, slot_tensors):
            return None
        self._checked.add(graph_key)
        return dict(zip(names, graph(render, gt, *slot_tensors)))

    def _region(self, plan: fused.BandPlan | None, weights: Tensor | None, present: list[bool]) -> Callable[..., Any]:
        """The captured function: (render, gt, *the slot target's tensors) -> (main_loss, *active frequency terms)."""
        lam = self.ssim_lambda
        frequency = self.frequency_loss

        def region(render: Tensor, gt: Tensor, *slot_tensors: Tensor) -> tuple[Tensor, ...]:
            pred, target = channels_first(render), channels_first(gt)
            outputs = [(1 - lam) * l1(pred, target) + lam * dssim(pred, target)]
            if frequency is not None and plan is not None:
                given = iter(slot_tensors)
                slots = fused.SlotTarget(*(next(given) if here else None for here in present))
                outputs += list(frequency.fused_terms(fused.as_planes(pred), plan, slots, weights).values())
            return tuple(outputs)

        return region

    def _agrees_with_eager(self, graph: Callable[..., Any], render: Tensor, gt: Tensor, key: Hashable | None,
                           slot_tensors: tuple[Tensor, ...]) -> bool:
        """One replay against the eager loss, values and gradient (the first use of each size; a host read)."""
        probe = render.detach().clone().requires_grad_(True)
        replayed = graph(probe, gt, *slot_tensors)
        replayed_grad = torch.autograd.grad(torch.stack(list(replayed)).sum(), probe)[0]
        probe = render.detach().clone().requires_grad_(True)
        expected = list(self.eager(probe, gt, key).values())
        expected_grad = torch.autograd.grad(torch.stack(expected).sum(), probe)[0]
        values_agree = torch.allclose(torch.stack(list(replayed)), torch.stack(expected), rtol=GRAPH_CHECK_RTOL,
                                      atol=1e-7)
        scale = expected_grad.abs().max().clamp_min(1e-30)
        grads_agree = bool(((replayed_grad - expected_grad).abs().max() / scale) <= GRAPH_CHECK_RTOL)
        if values_agree and grads_agree:
            return True
        self._turn_off(f"the captured image loss at {tuple(render.shape[:2])} disagrees with the eager one")
        return False

    def _turn_off(self, reason: str) -> None:
        self.cuda_graphs = False
        self._graphs.clear()
        warnings.warn(f"{reason}: CUDA graphs of the image loss are off for this run (the eager loss goes on)",
                      stacklevel=3)
