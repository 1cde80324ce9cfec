"""Adam parameter groups and learning-rate schedules, nerfstudio style (one optimizer per Gaussian parameter group).

Splatfacto 1.1.5's groups (``nerfstudio/configs/method_configs.py``): means 1.6e-4 decaying exponentially to 1.6e-6
over 30000 steps, features_dc 2.5e-3, features_rest 2.5e-3 / 20, opacities 0.05, scales 5e-3, quats 1e-3, all Adam
with eps 1e-15.

Schedules are nominal, as in nerfstudio: the decay runs over the scheduler's own ``max_steps`` (30000 for the means)
times the model's ``steps_scale``, never over the run's ``--max-num-iterations``. A run cut short is therefore the
first N steps of the full run (at step 500 of an 800-step run the means rate is 1.48e-4, as in a 30000-step run).

One optimizer per group (rather than one Adam with several groups) is what density control needs: the tensor surgery
in :mod:`kc_splatfacto.model.ops` replaces a group's parameter and rewrites that optimizer's state alone.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch

from kc_splatfacto.model.splatfacto import scale_steps
from kc_splatfacto.settings import integer, real, setting

ADAM_EPS = 1e-15
SPLATFACTO_SCHEDULE_STEPS = 30000
"""length of Splatfacto's nominal schedule (its means learning-rate decay and ``max_num_iterations``)"""


@dataclass
class AdamOptimizerConfig:
    """Adam for one parameter group."""

    lr: float = setting(1e-3, real(0.0, low_open=True))
    eps: float = setting(ADAM_EPS, real(0.0, low_open=True))
    weight_decay: float = setting(0.0, real(0.0))

    fused: bool = True
    """torch's fused Adam kernel (CPU and CUDA; same update, ~5x faster than the per-tensor loop on CPU here)"""

    def setup(self, params: list[torch.nn.Parameter]) -> torch.optim.Adam:
        return torch.optim.Adam(params, lr=self.lr, eps=self.eps, weight_decay=self.weight_decay,
                                fused=self.fused or None)


@dataclass
class ExponentialDecaySchedulerConfig:
    """lr(t) = exp((1 - t) log(lr_init) + t log(lr_final)), t = clip((step - warmup) / (max_steps - warmup), 0, 1).

    During the optional warm-up the rate ramps linearly from ``lr_pre_warmup`` (nerfstudio's ``ramp="linear"``).
    ``max_steps`` and ``warmup_steps`` are nominal: ``setup`` multiplies them by the model's ``steps_scale`` (like every
    other step-based schedule) and nothing else, so the schedule never depends on the run's length.
    """

    lr_final: float = setting(1e-6, real(0.0, low_open=True))
    max_steps: int | None = setting(SPLATFACTO_SCHEDULE_STEPS, integer(1, optional=True))
    """nominal decay length (None, as in configs saved before schedules were nominal, reads as 30000)"""
    warmup_steps: int = setting(0, integer(0))
    lr_pre_warmup: float = setting(1e-8, real(0.0))

    def setup(self, optimizer: torch.optim.Optimizer, steps_scale: float = 1.0) -> torch.optim.lr_scheduler.LambdaLR:
        if steps_scale <= 0:
            raise ValueError(f"steps_scale must be > 0, got {steps_scale}")
        nominal = self.max_steps if self.max_steps is not None else SPLATFACTO_SCHEDULE_STEPS
        steps = scale_steps(nominal, steps_scale)
        warmup = scale_steps(self.warmup_steps, steps_scale, at_least=0)
        return torch.optim.lr_scheduler.LambdaLR(
            optimizer, ExponentialDecay(optimizer.defaults["lr"], self.lr_final, steps, warmup, self.lr_pre_warmup)
        )


class ExponentialDecay:
    """The multiplicative factor of :class:`ExponentialDecaySchedulerConfig` (a picklable callable for LambdaLR)."""

    def __init__(self, lr_init: float, lr_final: float, max_steps: int, warmup_steps: int = 0, lr_pre_warmup: float = 1e-8):
        if lr_init <= 0 or lr_final <= 0:
            raise ValueError(f"exponential decay needs positive rates, got lr_init={lr_init}, lr_final={lr_final}")
        self.lr_init, self.lr_final = lr_init, lr_final
        self.max_steps, self.warmup_steps, self.lr_pre_warmup = max(int(max_steps), 1), int(warmup_steps), lr_pre_warmup

    def __call__(self, step: int) -> float:
        if step < self.warmup_steps:
            lr = self.lr_pre_warmup + (self.lr_init - self.lr_pre_warmup) * step / self.warmup_steps
        else:
            span = max(self.max_steps - self.warmup_steps, 1)
            t = min(max((step - self.warmup_steps) / span, 0.0), 1.0)
            lr = math.exp(math.log(self.lr_init) * (1 - t) + math.log(self.lr_final) * t)
        return lr / self.lr_init


@dataclass
class ParamGroupConfig:
    """Optimizer (and optional schedule) of one Gaussian parameter group."""

    optimizer: AdamOptimizerConfig = field(default_factory=AdamOptimizerConfig)
    scheduler: ExponentialDecaySchedulerConfig | None = None


def _group(lr: float, scheduler: ExponentialDecaySchedulerConfig | None = None) -> ParamGroupConfig:
    return ParamGroupConfig(optimizer=AdamOptimizerConfig(lr=lr), scheduler=scheduler)


@dataclass
class OptimizersConfig:
    """Splatfacto 1.1.5's parameter groups; field names equal the model's parameter group names (``model.parameter_groups()``)."""

    means: ParamGroupConfig = field(
        default_factory=lambda: _group(
            1.6e-4, ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=SPLATFACTO_SCHEDULE_STEPS)
        )
    )
    features_dc: ParamGroupConfig = field(default_factory=lambda: _group(0.0025))
    features_rest: ParamGroupConfig = field(default_factory=lambda: _group(0.0025 / 20))
    opacities: ParamGroupConfig = field(default_factory=lambda: _group(0.05))
    scales: ParamGroupConfig = field(default_factory=lambda: _group(0.005))
    quats: ParamGroupConfig = field(default_factory=lambda: _group(0.001))

    def group_names(self) -> list[str]:
        return ["means", "features_dc", "features_rest", "opacities", "scales", "quats"]

    def setup(
        self, params: Mapping[str, torch.nn.Parameter], steps_scale: float = 1.0
    ) -> tuple[dict[str, torch.optim.Optimizer], dict[str, torch.optim.lr_scheduler.LRScheduler]]:
        """One Adam per group (keyed like ``params``) and the schedules of the groups that have one, their nominal
        lengths multiplied by ``steps_scale`` (the model's)."""
        missing = [name for name in self.group_names() if name not in params]
        if missing:
            raise KeyError(f"optimizer groups {missing} have no parameter in the model (has {list(params.keys())})")
        optimizers: dict[str, torch.optim.Optimizer] = {}
        schedulers: dict[str, torch.optim.lr_scheduler.LRScheduler] = {}
        for name in self.group_names():
            group: ParamGroupConfig = getattr(self, name)
            optimizers[name] = group.optimizer.setup([params[name]])
            if group.scheduler is not None:
                schedulers[name] = group.scheduler.setup(optimizers[name], steps_scale)
        return optimizers, schedulers
