"""Adaptive density control of 3DGS (gsplat 1.5's ``DefaultStrategy``, as Splatfacto 1.1.5 configures it).

Usage, in a training loop::

    strategy = DefaultStrategy(grow_grad2d=0.0008, absgrad=True, prune_opa=0.1, prune_scale3d=0.5, ...)
    state = strategy.initialize_state(scene_scale=scene_scale)
    for step in range(max_steps):
        render, alpha, info = rasterization(..., absgrad=strategy.absgrad)
        strategy.step_pre_backward(params, optimizers, state, step, info)   # keeps means2d's gradient
        loss.backward()
        for opt in optimizers.values():
            opt.step(); opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(params, optimizers, state, step, info)  # grow / prune / reset opacity

Semantics (gsplat 1.5.3): the 2D mean gradient of every visible Gaussian is scaled to NDC-like units
(x by width/2 * n_cameras, y by height/2 * n_cameras) and its norm accumulated. Every ``refine_every`` steps after
``refine_start_iter`` (and before ``refine_stop_iter``, skipping the ``pause_refine_after_reset`` steps following each
opacity reset) Gaussians whose mean accumulated gradient exceeds ``grow_grad2d`` are duplicated when small
(max scale <= ``grow_scale3d`` x scene scale) or split in two when large (or, before ``refine_scale2d_stop_iter``,
when their screen radius exceeds ``grow_scale2d`` of the image); then Gaussians with opacity < ``prune_opa`` are
removed, and after the first opacity reset also those larger than ``prune_scale3d`` x scene scale (or, before
``refine_scale2d_stop_iter``, than ``prune_scale2d`` of the screen). Every ``reset_every`` steps opacities are
clamped to 2 ``prune_opa``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from kc_splatfacto import backend
from kc_splatfacto.model import ops


def _stats_kernel_applies(grads: torch.Tensor, radii: torch.Tensor, state: dict[str, Any]) -> bool:
    """The compiled statistics pass covers one camera of CPU float32 gradients with per-axis radii (training);
    several cameras keep the torch ops, whose duplicate-index radius update it does not reproduce."""
    stats = [state["grad2d"], state["count"]] + ([state["radii"]] if state.get("radii") is not None else [])
    return (
        backend.compiled(grads) and grads.dtype == torch.float32 and grads.dim() == 3 and grads.shape[0] == 1
        and radii.dim() == 3 and radii.dtype == torch.int32 and radii.shape == grads.shape
        and all(t.dtype == torch.float32 and t.is_contiguous() and t.shape[0] == grads.shape[1] for t in stats)
        and grads.is_contiguous() and radii.is_contiguous()
    )


class NoGaussiansLeftError(RuntimeError):
    """Density control removed every Gaussian."""


PARAMETER_NAMES = ("means", "scales", "quats", "opacities", "features_dc", "features_rest")
"""the Gaussians' parameters density control cuts and grows (each with an optimizer of the same name)"""


@runtime_checkable
class DensityStrategy(Protocol):
    """What a training loop calls on density control: gsplat's ``Strategy`` (``check_sanity``,
    ``initialize_state``, ``step_pre_backward``, ``step_post_backward``), plus ``refines_at`` (the steps whose host
    work a device-side verdict cannot replace) and ``cap`` (a memory budget reached). :class:`DefaultStrategy` and
    :class:`~kc_splatfacto.model.mcmc.MCMCStrategy` implement it; the loop never asks which one it holds."""

    absgrad: bool
    """whether the rasterizer must give the absolute screen-space gradients"""

    def check_sanity(self, params, optimizers) -> None: ...

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]: ...

    def step_pre_backward(self, params, optimizers, state: dict[str, Any], step: int,
                          info: dict[str, Any]) -> None: ...

    def step_post_backward(self, params, optimizers, state: dict[str, Any], step: int, info: dict[str, Any],
                           lr: float, noise_factor: torch.Tensor | None = None) -> dict[str, int]: ...
    """after the optimizers' step: the strategy's statistics and refinement; ``lr`` is the means' learning rate after
    this step's schedule update and ``noise_factor`` a device scalar multiplying any noise (0: the device's verdict
    rejected the step), for a strategy that perturbs the means (MCMC)"""

    def refines_at(self, step: int) -> bool: ...

    def cap(self, count: int) -> None: ...


def check_parameters(params, optimizers, who: str) -> None:
    """gsplat's sanity check: every parameter density control cuts and grows is there with its optimizer."""
    missing = [name for name in PARAMETER_NAMES if name not in params or name not in optimizers]
    if missing:
        raise KeyError(f"{who}: the Gaussians need the parameters and optimizers {list(PARAMETER_NAMES)}; "
                       f"missing {missing}")


def as_density_strategy(strategy: Any) -> DensityStrategy:
    """``strategy`` if it has the :class:`DensityStrategy` interface, else a TypeError naming what it lacks."""
    lacking = [name for name in ("absgrad", "check_sanity", "initialize_state", "step_pre_backward",
                                 "step_post_backward", "refines_at", "cap") if not hasattr(strategy, name)]
    if lacking:
        raise TypeError(f"{type(strategy).__name__} is not a density strategy: it lacks {', '.join(lacking)} "
                        "(kc_splatfacto.model.strategy.DensityStrategy; DefaultStrategy and MCMCStrategy have them)")
    return strategy


@dataclass
class DefaultStrategy:
    """Splatfacto 1.1.5's values are set by ``SplatfactoModelConfig``; the defaults here are gsplat's."""

    prune_opa: float = 0.005
    grow_grad2d: float = 0.0002
    grow_scale3d: float = 0.01
    grow_scale2d: float = 0.05
    prune_scale3d: float = 0.1
    prune_scale2d: float = 0.15
    refine_scale2d_stop_iter: int = 0
    refine_start_iter: int = 500
    refine_stop_iter: int = 15_000
    reset_every: int = 3000
    refine_every: int = 100
    pause_refine_after_reset: int = 0
    absgrad: bool = False
    revised_opacity: bool = False
    n_split_samples: int = 2
    max_gaussians: int | None = None
    """growth cap (not in gsplat's DefaultStrategy): when a refinement would exceed it, only the candidates with the
    largest accumulated gradient grow. Guards small machines against runaway densification (tiny images give every
    Gaussian a large 2D gradient, and the count doubles at each refinement until memory runs out)."""
    key_for_gradient: str = "means2d"

    def check_sanity(self, params, optimizers) -> None:
        """Every parameter it grows and prunes is there, with its optimizer."""
        check_parameters(params, optimizers, "DefaultStrategy")

    def cap(self, count: int) -> None:
        """Grow no Gaussians past ``count`` from now on (``max_gaussians`` lowered, never raised)."""
        self.max_gaussians = int(count) if self.max_gaussians is None else min(int(self.max_gaussians), int(count))

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """Running statistics: ``grad2d`` [N] and ``count`` [N] (and ``radii`` [N]), created lazily."""
        state: dict[str, Any] = {"grad2d": None, "count": None, "scene_scale": float(scene_scale)}
        if self.refine_scale2d_stop_iter > 0:
            state["radii"] = None
        return state

    def step_pre_backward(self, params, optimizers, state: dict[str, Any], step: int, info: dict[str, Any]) -> None:
        """Ask autograd to keep the gradient of the projected means (a non-leaf tensor)."""
        if self.key_for_gradient not in info:
            raise KeyError(f"rasterization meta has no '{self.key_for_gradient}' (keys: {sorted(info)})")
        means2d = info[self.key_for_gradient]
        if means2d.requires_grad:
            means2d.retain_grad()

    def step_post_backward(
        self, params, optimizers, state: dict[str, Any], step: int, info: dict[str, Any], lr: float = 0.0,
        noise_factor: torch.Tensor | None = None,
    ) -> dict[str, int]:
        """Accumulate statistics, then grow/prune/reset on the schedule. Returns counts of what it did. (``lr`` and
        ``noise_factor``, the interface's, are MCMC's: this strategy adds no noise.)"""
        report = {"duplicated": 0, "split": 0, "pruned": 0, "opacity_reset": 0}
        if step >= self.refine_stop_iter:
            return report
        self._update_state(params, state, info)
        if self._grows_at(step):
            report["duplicated"], report["split"] = self._grow_gs(params, optimizers, state, step)
            report["pruned"] = self._prune_gs(params, optimizers, state, step)
            state["grad2d"].zero_()
            state["count"].zero_()
            if self.refine_scale2d_stop_iter > 0:
                state["radii"].zero_()
            if len(params["means"]) == 0:
                raise NoGaussiansLeftError(
                    f"density control at step {step} removed every Gaussian (opacity < {self.prune_opa} or larger "
                    f"than {self.prune_scale3d} x scene scale {state['scene_scale']:.4g}); check the scene scale "
                    f"and the initialization, or lower --pipeline.model.cull-alpha-thresh"
                )
        if self._resets_at(step):
            ops.reset_opa(params, optimizers, state, value=self.prune_opa * 2.0)
            report["opacity_reset"] = 1
        return report

    def refines_at(self, step: int) -> bool:
        """Whether ``step_post_backward`` at ``step`` does more than accumulate statistics (grows, prunes or resets
        opacities): the steps whose host work a device-side step verdict cannot replace."""
        return step < self.refine_stop_iter and (self._grows_at(step) or self._resets_at(step))

    def _grows_at(self, step: int) -> bool:
        return (step > self.refine_start_iter and step % self.refine_every == 0
                and step % self.reset_every >= self.pause_refine_after_reset)

    def _resets_at(self, step: int) -> bool:
        return step % self.reset_every == 0 and step > 0

    @torch.no_grad()
    def _update_state(self, params, state: dict[str, Any], info: dict[str, Any]) -> None:
        means2d = info[self.key_for_gradient]
        grads = means2d.absgrad if self.absgrad else means2d.grad
        if grads is None:
            kind = "absgrad" if self.absgrad else "grad"
            raise RuntimeError(
                f"meta['{self.key_for_gradient}'].{kind} is empty: call step_pre_backward before backward"
                + (" and rasterize with absgrad=True" if self.absgrad else "")
            )
        n_gaussian = len(params["means"])
        device = grads.device
        if state["grad2d"] is None:
            state["grad2d"] = torch.zeros(n_gaussian, device=device)
        if state["count"] is None:
            state["count"] = torch.zeros(n_gaussian, device=device)
        if self.refine_scale2d_stop_iter > 0 and state["radii"] is None:
            state["radii"] = torch.zeros(n_gaussian, device=device)
        radii = info["radii"]
        if _stats_kernel_applies(grads, radii, state):
            # one compiled pass instead of ~10 tensor ops; same float32 results bit for bit (tests/model)
            from kc_splatfacto.model._strategy_kernels import accumulate_screen_stats

            track = self.refine_scale2d_stop_iter > 0
            accumulate_screen_stats(
                grads[0].detach().numpy(), radii[0].numpy(), np.float32(info["width"] / 2.0),
                np.float32(info["height"] / 2.0), np.float32(max(info["width"], info["height"])),
                state["grad2d"].numpy(), state["count"].numpy(),
                state["radii"].numpy() if track else np.empty(0, np.float32),
            )
            return
        grads = grads.clone()
        grads[..., 0] *= info["width"] / 2.0 * info["n_cameras"]
        grads[..., 1] *= info["height"] / 2.0 * info["n_cameras"]
        if radii.dim() == 3:  # gsplat 1.5: per-axis radii [C, N, 2]
            sel = (radii > 0).all(dim=-1)
            radii_max = radii.max(dim=-1).values
        else:
            sel = radii > 0
            radii_max = radii
        # masked sums over the cameras rather than gsplat's index_add_ of the selected entries: no nonzero() or
        # boolean indexing, so no host synchronisation on CUDA; adding +0.0 where a Gaussian is not seen leaves its
        # statistics bit for bit as they were (one camera: the same float32 sums as gsplat's)
        state["grad2d"] += torch.where(sel, grads.norm(dim=-1), 0.0).sum(dim=0)
        state["count"] += sel.sum(dim=0, dtype=state["count"].dtype)
        if self.refine_scale2d_stop_iter > 0:
            seen = torch.where(sel, radii_max.float(), 0.0).amax(dim=0) / float(max(info["width"], info["height"]))
            state["radii"] = torch.maximum(state["radii"], seen)

    @torch.no_grad()
    def _grow_gs(self, params, optimizers, state: dict[str, Any], step: int) -> tuple[int, int]:
        grads = state["grad2d"] / state["count"].clamp_min(1)
        is_grad_high = grads > self.grow_grad2d
        is_small = torch.exp(params["scales"]).max(dim=-1).values <= self.grow_scale3d * state["scene_scale"]
        is_dupli = is_grad_high & is_small
        n_dupli = int(is_dupli.sum())
        is_split = is_grad_high & ~is_small
        if step < self.refine_scale2d_stop_iter:
            is_split |= state["radii"] > self.grow_scale2d
        if self.max_gaussians is not None:
            is_dupli, is_split = self._cap_growth(grads, is_dupli, is_split, len(params["means"]), self.max_gaussians)
            n_dupli = int(is_dupli.sum())
        n_split = int(is_split.sum())
        if n_dupli > 0:
            ops.duplicate(params, optimizers, state, is_dupli)
        # copies made by duplication are not split in the same round
        is_split = torch.cat([is_split, torch.zeros(n_dupli, dtype=torch.bool, device=is_split.device)])
        if n_split > 0:
            ops.split(params, optimizers, state, is_split, self.n_split_samples, self.revised_opacity)
        return n_dupli, n_split

    def _cap_growth(
        self, grads: torch.Tensor, is_dupli: torch.Tensor, is_split: torch.Tensor, n_gaussian: int, max_gaussians: int
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Keep the highest-gradient candidates whose added Gaussians fit under ``max_gaussians``."""
        budget = max(max_gaussians - n_gaussian, 0)
        cost = is_dupli.long() + is_split.long() * (self.n_split_samples - 1)
        if int(cost.sum()) <= budget:
            return is_dupli, is_split
        order = torch.argsort(torch.where(cost > 0, grads, torch.full_like(grads, -1.0)), descending=True, stable=True)
        keep = torch.zeros_like(is_dupli)
        keep[order] = torch.cumsum(cost[order], 0) <= budget
        return is_dupli & keep, is_split & keep

    @torch.no_grad()
    def _prune_gs(self, params, optimizers, state: dict[str, Any], step: int) -> int:
        is_prune = torch.sigmoid(params["opacities"].flatten()) < self.prune_opa
        if step > self.reset_every:
            is_too_big = torch.exp(params["scales"]).max(dim=-1).values > self.prune_scale3d * state["scene_scale"]
            if step < self.refine_scale2d_stop_iter:
                is_too_big |= state["radii"] > self.prune_scale2d
            is_prune |= is_too_big
        n_prune = int(is_prune.sum())
        if n_prune > 0:
            ops.remove(params, optimizers, state, is_prune)
        return n_prune
