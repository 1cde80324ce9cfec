"""MCMC densification ("3D Gaussian Splatting as Markov Chain Monte Carlo", Kheradmand et al. 2024): gsplat 1.5.3's
``MCMCStrategy`` with its interface and semantics, on the CPU and on CUDA.

Usage, in a training loop (``lr``: the means' learning rate after this step's schedule update, as gsplat's
``simple_trainer`` and nerfstudio pass it)::

    strategy = MCMCStrategy(cap_max=300_000, noise_lr=5e5, min_opacity=0.005)
    state = strategy.initialize_state()
    for step in range(max_steps):
        render, alpha, info = rasterization(...)
        strategy.step_pre_backward(params, optimizers, state, step, info)   # nothing to keep
        loss.backward()
        for opt in optimizers.values():
            opt.step(); opt.zero_grad(set_to_none=True)
        strategy.step_post_backward(params, optimizers, state, step, info, lr=means_lr)

Every ``refine_every`` steps strictly between ``refine_start_iter`` and ``refine_stop_iter``: the dead Gaussians
(opacity <= ``min_opacity``) are moved onto live ones drawn by opacity (``ops.relocate``), then min(cap_max, 1.05 N) - N
new ones are drawn the same way (``ops.sample_add``): the count never passes ``cap_max`` once it starts below it.
Every step: the means get noise scaled by ``lr x noise_lr`` (``ops.inject_noise_to_position``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from kc_splatfacto.errors import UserError
from kc_splatfacto.model import ops
from kc_splatfacto.model.strategy import NoGaussiansLeftError, check_parameters

GROWTH_PER_REFINEMENT = 1.05
"""each refinement adds Gaussians up to 1.05 times the count (gsplat's and the paper's), capped by ``cap_max``"""


class GaussianCapError(UserError, ValueError):
    """The run starts with more Gaussians than its cap allows."""


@dataclass
class MCMCStrategy:
    """Splatfacto's values are set by ``SplatfactoModelConfig`` (``strategy="mcmc"``); the defaults here are
    gsplat's."""

    cap_max: int = 1_000_000
    """most Gaussians the run may hold"""
    noise_lr: float = 5e5
    """the means' noise is scaled by this times their learning rate"""
    refine_start_iter: int = 500
    refine_stop_iter: int = 25_000
    refine_every: int = 100
    min_opacity: float = 0.005
    """Gaussians at or below this opacity are dead: relocated at each refinement"""
    absgrad = False
    """what the rasterizer is asked for (MCMC reads no screen-space gradient): nerfstudio's ``get_outputs`` passes
    ``strategy.absgrad`` whichever strategy it holds (a class attribute, not a setting)"""

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        """The running state: empty (``scene_scale``, the interface's, is not read). gsplat keeps its binomial table here; ours is a cached constant
        (:func:`~kc_splatfacto.model.relocation.binomial_table`), so that the state holds only per-Gaussian rows,
        which the tensor surgery of ``ops`` (non-finite removal included) cuts and grows with the Gaussians."""
        return {}

    def check_sanity(self, params, optimizers) -> None:
        """Every parameter it relocates and adds is there with its optimizer, and the run starts within its cap."""
        check_parameters(params, optimizers, "MCMCStrategy")
        self.check_initial_count(len(params["means"]))

    def cap(self, count: int) -> None:
        """Hold no more than ``count`` Gaussians from now on (``cap_max`` lowered, never raised)."""
        self.cap_max = min(int(self.cap_max), int(count))

    def check_initial_count(self, n_gaussians: int) -> None:
        """Raise GaussianCapError when the run would start above its cap (relocation and growth never shrink it)."""
        if n_gaussians > self.cap_max:
            raise GaussianCapError(
                f"max_gs_num ({self.cap_max}) is smaller than the {n_gaussians} initial Gaussians (seed points or "
                f"num_random): raise --pipeline.model.max-gs-num to at least {n_gaussians}"
            )

    def step_pre_backward(self, params, optimizers, state: dict[str, Any], step: int, info: dict[str, Any]) -> None:
        """Nothing: MCMC reads no screen-space gradient."""

    def refines_at(self, step: int) -> bool:
        """Whether ``step_post_backward`` at ``step`` relocates and adds (host work), beside the noise of every step."""
        return self.refine_start_iter < step < self.refine_stop_iter and step % self.refine_every == 0

    def step_post_backward(
        self, params, optimizers, state: dict[str, Any], step: int, info: dict[str, Any], lr: float,
        noise_factor: torch.Tensor | None = None,
    ) -> dict[str, int]:
        """Relocate and add on the schedule, then inject noise (``lr``: the means' learning rate; ``noise_factor``, a
        device scalar, multiplies the noise: 0 for a step whose update the device's verdict rejected). Returns the
        counts of what it did."""
        report = {"relocated": 0, "added": 0}
        if self.refines_at(step):
            report["relocated"] = self._relocate_gs(params, optimizers, state, step)
            report["added"] = self._add_new_gs(params, optimizers, state)
        ops.inject_noise_to_position(params, optimizers, state, scaler=lr * self.noise_lr, factor=noise_factor)
        return report

    @torch.no_grad()
    def _relocate_gs(self, params, optimizers, state: dict[str, Any], step: int) -> int:
        dead = torch.sigmoid(params["opacities"].detach().flatten()) <= self.min_opacity
        n_dead = int(dead.sum())
        if n_dead == len(dead) and n_dead > 0:
            raise NoGaussiansLeftError(
                f"MCMC densification at step {step}: every Gaussian's opacity is <= {self.min_opacity}, none is left "
                f"to relocate the dead ones onto; lower --pipeline.model.cull-alpha-thresh"
            )
        return ops.relocate(params, optimizers, state, dead, self.min_opacity) if n_dead else 0

    @torch.no_grad()
    def _add_new_gs(self, params, optimizers, state: dict[str, Any]) -> int:
        n_now = len(params["means"])
        n_new = max(0, min(self.cap_max, int(GROWTH_PER_REFINEMENT * n_now)) - n_now)
        if n_new > 0:
            ops.sample_add(params, optimizers, state, n_new, self.min_opacity)
        return n_new


def splatfacto_mcmc(fields: Any, warmup_length: int, stop_split_at: int, refine_every: int) -> MCMCStrategy:
    """nerfstudio main's MCMC from a Splatfacto model config's fields (``max_gs_num``, ``noise_lr``,
    ``cull_alpha_thresh``: dead below it) and its step counts (kc-train's after ``steps_scale``); the one mapping both
    models use."""
    return MCMCStrategy(cap_max=fields.max_gs_num, noise_lr=fields.noise_lr, refine_start_iter=warmup_length,
                        refine_stop_iter=stop_split_at, refine_every=refine_every,
                        min_opacity=fields.cull_alpha_thresh)


def mcmc_regularization(fields: Any, opacities: torch.Tensor, scales: torch.Tensor) -> dict[str, torch.Tensor]:
    """nerfstudio main's MCMC loss terms from a model config's ``mcmc_opacity_reg`` and ``mcmc_scale_reg``:
    ``mcmc_opacity_reg`` x mean opacity and ``mcmc_scale_reg`` x mean scale, each only when its weight is non-zero
    (``opacities``: logits, ``scales``: log scales). Transparent Gaussians are what relocation moves, so the opacity
    term feeds it."""
    terms = {}
    if fields.mcmc_opacity_reg > 0:
        terms["mcmc_opacity_reg"] = fields.mcmc_opacity_reg * torch.sigmoid(opacities).abs().mean()
    if fields.mcmc_scale_reg > 0:
        terms["mcmc_scale_reg"] = fields.mcmc_scale_reg * torch.exp(scales).abs().mean()
    return terms
