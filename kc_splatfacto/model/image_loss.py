"""The image-space loss of a training render: Splatfacto's main loss and KC-3DGS's frequency terms as one region,
replayed as a CUDA graph per image size on a GPU.

On CUDA a training step is bound by kernel launches, and this region (L1, D-SSIM, the DWT, the band statistics and
their backwards) is ~150 of them. :class:`ImageLoss` captures it once per training resolution with
``torch.cuda.make_graphed_callables`` and replays it: a copy of the inputs and one graph launch each way. What the
graph reads is passed in as tensors (the render, the ground truth, the ground truth's cached wavelet target), so one
graph serves every training image of a size. The graph holds the frequency terms with a fused kernel
(:meth:`FrequencyLoss.stage`); a term without one runs eagerly beside the replay. The first replay of each size is
checked against the eager computation, values and gradient; a failed capture or a mismatch turns the graphs off for
the run with one warning, and the eager loss goes on. Elsewhere (the CPU) the loss is always eager.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Hashable
from typing import Any

import torch
from torch import Tensor

from kc_splatfacto.losses.frequency import FrequencyLoss, FrequencyStage
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
        if self.frequency_loss is not None and self.frequency_loss.active:
            # the same view of the render as the main loss's: the gradients of all terms meet in one node, summed in
            # one order (a second view would sum them in another: other float rounding, another whole-run hash)
            losses.update(self.frequency_loss.stage(pred, target, key).losses(pred))
        return losses

    # ----------------------------------------------------------------------------------------------- graphs
    def _graphs_apply(self, render: Tensor, gt: Tensor) -> bool:
        return (render.device.type == "cuda" and render.requires_grad and render.dtype == torch.float32
                and gt.dtype == render.dtype and torch.is_grad_enabled())

    def _graphed(self, render: Tensor, gt: Tensor, key: Hashable | None) -> dict[str, Tensor] | None:
        """The terms through the size's graph (captured and checked on first use): the main loss and the frequency
        terms with a fused kernel in the graph, the other frequency terms (the table's unfused ones, or all of them
        where the fused path does not serve) eagerly beside it; None where graphs have been turned off."""
        frequency = self.frequency_loss
        stage: FrequencyStage | None = None
        if frequency is not None and frequency.active:
            stage = frequency.stage(channels_first(render), channels_first(gt), key)
        tensors = () if stage is None else stage.tensors
        names = ("main_loss", *(() if stage is None else stage.fused_names))
        graph_key = (tuple(render.shape), None if stage is None else stage.graph_key)
        graph = self._graphs.get(graph_key)
        if graph is None:
            region = self._region(stage)
            sample = (render.detach().clone().requires_grad_(True), gt.detach().clone(), *(t.clone() for t in tensors))
            try:
                graph = self._graphs[graph_key] = self._capture(region, sample)
            except Exception as error:  # noqa: BLE001  (any failure to capture leaves the eager loss in charge)
                self._turn_off(f"capturing the image loss at {tuple(render.shape[:2])} failed ({error})")
                return None
        if graph_key not in self._checked and not self._agrees_with_eager(graph, render, gt, key, tensors, names):
            return None
        self._checked.add(graph_key)
        outputs = graph(render, gt, *tensors)
        losses = {"main_loss": outputs[0]}
        if stage is not None:
            losses.update(stage.combine(outputs[1:], channels_first(render)))
        return losses

    def _region(self, stage: FrequencyStage | None) -> Callable[..., Any]:
        """The captured function: (render, gt, *the fused terms' ground-truth tensors) -> (main_loss, *the fused
        terms). It reads only what every image of the graph's size shares (the stage's plan and weights)."""
        lam = self.ssim_lambda

        def region(render: Tensor, gt: Tensor, *tensors: Tensor) -> tuple[Tensor, ...]:
            pred, target = channels_first(render), channels_first(gt)
            outputs = [(1 - lam) * l1(pred, target) + lam * dssim(pred, target)]
            if stage is not None:
                outputs += stage.fused(pred, *tensors)
            return tuple(outputs)

        return region

    def _agrees_with_eager(self, graph: Callable[..., Any], render: Tensor, gt: Tensor, key: Hashable | None,
                           tensors: tuple[Tensor, ...], names: tuple[str, ...]) -> bool:
        """One replay against the eager loss's same terms, values and gradient (the first use of each size; a host
        read)."""
        probe = render.detach().clone().requires_grad_(True)
        replayed = graph(probe, gt, *tensors)
        replayed_grad = torch.autograd.grad(torch.stack(list(replayed)).sum(), probe)[0]
        probe = render.detach().clone().requires_grad_(True)
        eager = self.eager(probe, gt, key)
        expected = [eager[name] for name in names]
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
