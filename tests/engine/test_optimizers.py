"""engine/optimizers.py against independent oracles: the learning-rate schedule against nerfstudio's
ExponentialDecayScheduler written out here in float64 numpy and against torch's own LinearLR / ExponentialLR where
they coincide; the Adam groups against torch.optim.Adam built by hand (the for-loop implementation, not the fused
kernel the module asks for); the optimizer and schedule state through a weights-only checkpoint."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from kc_splatfacto.engine.checkpoints import load_checkpoint, save_checkpoint
from kc_splatfacto.engine.optimizers import (
    AdamOptimizerConfig,
    ExponentialDecay,
    ExponentialDecaySchedulerConfig,
    OptimizersConfig,
    ParamGroupConfig,
)

#: Splatfacto 1.1.5's Adam rates (nerfstudio/configs/method_configs.py), written out here as the oracle
SPLATFACTO_RATES = {"means": 1.6e-4, "features_dc": 2.5e-3, "features_rest": 2.5e-3 / 20, "opacities": 0.05,
                    "scales": 5e-3, "quats": 1e-3}
SPLATFACTO_EPS = 1e-15
#: [N, ...] shapes of each group for a 7-Gaussian, SH degree 1 model
SHAPES = {"means": (7, 3), "features_dc": (7, 3), "features_rest": (7, 3, 3), "opacities": (7, 1), "scales": (7, 3),
          "quats": (7, 4)}


def nerfstudio_lr(step: int, lr_init: float, lr_final: float, max_steps: int, warmup_steps: int = 0,
                  lr_pre_warmup: float = 1e-8) -> float:
    """nerfstudio's ExponentialDecayScheduler with ``ramp="linear"`` (nerfstudio/engine/schedulers.py), float64."""
    if step < warmup_steps:
        return lr_pre_warmup + (lr_init - lr_pre_warmup) * step / warmup_steps
    t = np.clip((step - warmup_steps) / (max_steps - warmup_steps), 0.0, 1.0)
    return float(np.exp(np.log(lr_init) * (1 - t) + np.log(lr_final) * t))


def scheduled_rates(scheduler_config: ExponentialDecaySchedulerConfig, lr_init: float, steps: int,
                    steps_scale: float = 1.0) -> list[float]:
    """The rate of each of the first ``steps`` steps, read from a real Adam driven by the module's schedule."""
    param = torch.nn.Parameter(torch.zeros(2))
    optimizer = AdamOptimizerConfig(lr=lr_init).setup([param])
    scheduler = scheduler_config.setup(optimizer, steps_scale)
    rates = []
    for _ in range(steps):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    return rates


@pytest.mark.parametrize("lr_init, lr_final, max_steps, warmup, pre, steps_scale, steps", [
    (1.6e-4, 1.6e-6, 30000, 0, 1e-8, 0.01, 400),  # Splatfacto's means, compressed to 300 steps, then held
    (1e-2, 1e-4, None, 0, 1e-8, 0.005, 200),  # None reads as nerfstudio's 30000 (configs of earlier versions)
    (1e-2, 1e-4, 200, 50, 1e-6, 1.0, 260),  # linear warm-up from lr_pre_warmup, then the decay
    (5e-3, 5e-5, 200, 30, 0.0, 0.5, 130),  # warm-up and decay both compressed: 15 and 100 steps
])
def test_schedule_is_nerfstudios_exponential_decay(lr_init, lr_final, max_steps, warmup, pre, steps_scale, steps):
    config = ExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=max_steps, warmup_steps=warmup,
                                             lr_pre_warmup=pre)
    nominal = 30000 if max_steps is None else max_steps
    scaled_max, scaled_warmup = round(nominal * steps_scale), round(warmup * steps_scale)
    expected = [nerfstudio_lr(step, lr_init, lr_final, scaled_max, scaled_warmup, pre) for step in range(steps)]
    ours = scheduled_rates(config, lr_init, steps, steps_scale)
    np.testing.assert_allclose(ours, expected, rtol=1e-12, atol=0)
    assert ours[scaled_warmup] == pytest.approx(lr_init, rel=1e-12)
    if steps > scaled_max:  # held at lr_final once the (scaled) nominal length is over
        assert ours[scaled_max:] == pytest.approx([lr_final] * (steps - scaled_max), rel=1e-12)


def test_schedule_coincides_with_torchs_linear_then_exponential_schedulers():
    """Linear warm-up then a constant-ratio decay is torch's LinearLR followed by ExponentialLR (until max_steps)."""
    lr_init, lr_final, pre, warmup, max_steps = 1e-2, 1e-4, 1e-5, 20, 100
    param = torch.nn.Parameter(torch.zeros(2))
    optimizer = torch.optim.Adam([param], lr=lr_init)
    gamma = (lr_final / lr_init) ** (1 / (max_steps - warmup))
    torch_scheduler = torch.optim.lr_scheduler.SequentialLR(optimizer, [
        torch.optim.lr_scheduler.LinearLR(optimizer, pre / lr_init, 1.0, total_iters=warmup),
        torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma)], milestones=[warmup])
    expected = []
    for _ in range(max_steps + 1):
        expected.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        torch_scheduler.step()
    config = ExponentialDecaySchedulerConfig(lr_final=lr_final, max_steps=max_steps, warmup_steps=warmup,
                                             lr_pre_warmup=pre)
    np.testing.assert_allclose(scheduled_rates(config, lr_init, max_steps + 1), expected, rtol=1e-12, atol=0)


def test_schedule_length_is_nominal_times_steps_scale_only():
    """The decay ends at round(max_steps * steps_scale), whatever else: 30000 * 0.01 = 300, 30000 * 0.0101 = 303."""
    for steps_scale, end in ((0.01, 300), (0.0101, 303), (1e-9, 1)):
        rates = scheduled_rates(ExponentialDecaySchedulerConfig(lr_final=1e-6), 1e-4, end + 2, steps_scale)
        assert rates[end - 1] > 1e-6 * (1 + 1e-9) and rates[end] == pytest.approx(1e-6, rel=1e-12), steps_scale


@pytest.mark.parametrize("steps_scale", [0.0, -0.5])
def test_non_positive_steps_scale_is_refused(steps_scale):
    optimizer = torch.optim.Adam([torch.nn.Parameter(torch.zeros(1))], lr=1e-3)
    with pytest.raises(ValueError, match=f"steps_scale must be > 0, got {steps_scale}"):
        ExponentialDecaySchedulerConfig().setup(optimizer, steps_scale)


@pytest.mark.parametrize("lr_init, lr_final", [(0.0, 1e-6), (1e-3, 0.0), (-1e-3, 1e-6)])
def test_exponential_decay_needs_positive_rates(lr_init, lr_final):
    with pytest.raises(ValueError, match="exponential decay needs positive rates"):
        ExponentialDecay(lr_init, lr_final, max_steps=10)


def _params(dtype=torch.float64) -> torch.nn.ParameterDict:
    generator = torch.Generator().manual_seed(0)
    return torch.nn.ParameterDict({name: torch.nn.Parameter(torch.randn(shape, generator=generator, dtype=dtype))
                                   for name, shape in SHAPES.items()})


def _train(optimizers: dict, schedulers: dict, params: dict, steps: range, grad_scale: float = 1e-9) -> list[float]:
    """Adam steps on fixed pseudo-random gradients (tiny: Adam's eps then matters); the means' rate of each step."""
    rates = []
    for step in steps:
        generator = torch.Generator().manual_seed(1000 + step)
        for name in SHAPES:
            params[name].grad = grad_scale * torch.randn(SHAPES[name], generator=generator, dtype=params[name].dtype)
        rates.append(optimizers["means"].param_groups[0]["lr"])
        for optimizer in optimizers.values():
            optimizer.step()
        for scheduler in schedulers.values():
            scheduler.step()
    return rates


def _hand_built(params: dict, steps_scale: float, eps: float = SPLATFACTO_EPS, weight_decay: dict | None = None):
    """Splatfacto's optimizers built here from torch alone: one plain (for-loop) Adam per group, the means' decay a
    LambdaLR on the nerfstudio formula above."""
    weight_decay = weight_decay or {}
    optimizers = {name: torch.optim.Adam([params[name]], lr=lr, eps=eps, weight_decay=weight_decay.get(name, 0.0),
                                         foreach=False, fused=False)
                  for name, lr in SPLATFACTO_RATES.items()}
    decay_steps = round(30000 * steps_scale)
    schedulers = {"means": torch.optim.lr_scheduler.LambdaLR(
        optimizers["means"], lambda step: nerfstudio_lr(step, 1.6e-4, 1.6e-6, decay_steps) / 1.6e-4)}
    return optimizers, schedulers


@pytest.mark.parametrize("fused", [True, False])
def test_groups_train_like_hand_built_adams(fused):
    """Splatfacto's six groups (one Adam each, eps 1e-15, the means decaying) move the parameters as hand-built
    torch Adams do, step for step; with torch's default eps (1e-8) the same gradients would move them far less."""
    config = OptimizersConfig()
    for name in config.group_names():
        getattr(config, name).optimizer.fused = fused
    config.scales.optimizer.weight_decay = 0.01
    ours, reference, default_eps = _params(), _params(), _params()
    optimizers, schedulers = config.setup(ours, steps_scale=40 / 30000)
    assert set(optimizers) == set(SHAPES) and list(schedulers) == ["means"]
    for name, optimizer in optimizers.items():  # one tensor per optimizer: density control rewrites it alone
        assert len(optimizer.param_groups) == 1 and optimizer.param_groups[0]["params"] == [ours[name]]
    our_rates = _train(optimizers, schedulers, ours, range(50))
    reference_rates = _train(*_hand_built(reference, 40 / 30000, weight_decay={"scales": 0.01}), reference, range(50))
    _train(*_hand_built(default_eps, 40 / 30000, eps=1e-8, weight_decay={"scales": 0.01}), default_eps, range(50))
    np.testing.assert_allclose(our_rates, reference_rates, rtol=1e-12, atol=0)
    assert our_rates[40:] == pytest.approx([1.6e-6] * 10, rel=1e-12)
    start = _params()
    for name in SHAPES:
        torch.testing.assert_close(ours[name], reference[name], rtol=1e-12, atol=1e-15)
        if name != "scales":  # (its weight decay, not the tiny gradient, drives Adam there)
            moved, moved_default = (ours[name] - start[name]).abs().max(), (default_eps[name] - start[name]).abs().max()
            assert moved > 10 * moved_default, name  # eps 1e-15 reached Adam: gradients of 1e-9 still move by ~lr


def test_a_model_without_a_group_is_refused_naming_it():
    params = _params()
    del params["quats"]
    with pytest.raises(KeyError, match=r"optimizer groups \['quats'\] have no parameter in the model"):
        OptimizersConfig().setup(params)


def test_a_group_without_a_schedule_keeps_its_rate():
    config = OptimizersConfig(quats=ParamGroupConfig(optimizer=AdamOptimizerConfig(lr=0.002)))
    params = _params()
    optimizers, schedulers = config.setup(params, steps_scale=0.001)
    _train(optimizers, schedulers, params, range(60))
    assert optimizers["quats"].param_groups[0]["lr"] == 0.002 and "quats" not in schedulers


def test_optimizer_and_schedule_state_resume_bit_identically_from_a_weights_only_checkpoint(tmp_path):
    """30 steps, a checkpoint of the optimizers' and schedules' state (loaded weights-only: the schedule's callable
    is stored as plain numbers), 30 more steps from it: the same rates and parameters as 60 uninterrupted steps."""
    steps_scale = 40 / 30000
    straight = _params()
    optimizers, schedulers = OptimizersConfig().setup(straight, steps_scale)
    straight_rates = _train(optimizers, schedulers, straight, range(60))

    first = _params()
    optimizers, schedulers = OptimizersConfig().setup(first, steps_scale)
    rates = _train(optimizers, schedulers, first, range(30))
    path = save_checkpoint(tmp_path, 30, {
        "step": 30, "model": {name: p.detach() for name, p in first.items()},
        "optimizers": {k: o.state_dict() for k, o in optimizers.items()},
        "schedulers": {k: s.state_dict() for k, s in schedulers.items()}})
    checkpoint = load_checkpoint(path)
    resumed = torch.nn.ParameterDict({k: torch.nn.Parameter(v) for k, v in checkpoint["model"].items()})
    optimizers, schedulers = OptimizersConfig().setup(resumed, steps_scale)
    for name, state in checkpoint["optimizers"].items():
        optimizers[name].load_state_dict(state)
    for name, state in checkpoint["schedulers"].items():
        schedulers[name].load_state_dict(state)
    rates += _train(optimizers, schedulers, resumed, range(30, 60))
    assert rates == straight_rates
    for name in SHAPES:
        assert torch.equal(resumed[name], straight[name]), name
    assert math.isclose(rates[-1], 1.6e-6, rel_tol=1e-12)
