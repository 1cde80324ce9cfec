"""The step's verdict taken on the device (engine/training_state.py, ``machine.step_verdict``): fused Adam's
found_inf and a render made invisible to density control must leave the run exactly where the host's verdict leaves
it. Checked against the host verdict's run, step by step and bit for bit, with and without a bad step; that a bad
step changes no parameter, no Adam moment and no density statistic; and that the host still takes the verdict where it
must (refinement steps, unfused Adam, a strategy that does not say when it refines)."""

from __future__ import annotations

import pytest
import torch

from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.engine.training_state import TrainingState
from tests.training_utils import demo_pipeline, poison_loss_at, tiny_demo_config

STEPS = 40
BAD_STEP = 15  # an odd step: no refinement at the tiny config's compressed schedule (every 2 steps from step 10)


def train(tmp_path, method: str, device_verdict: bool, bad_step: int | None = None, fused: bool = True):
    """STEPS steps of a fresh state; returns (pipeline, state, one letter per step: D device verdict, H host, S host
    skipped, and the Gaussians after each step)."""
    pipeline, config = demo_pipeline(tmp_path, method, seed=0)
    if not fused:
        for name in config.optimizers.group_names():
            getattr(config.optimizers, name).optimizer.fused = False
    state = TrainingState(pipeline.model, config.optimizers, device_verdict=device_verdict)
    if bad_step is not None:
        poison_loss_at(pipeline.model, {bad_step})
    kinds, history = [], []
    for step in range(STEPS):
        result = state.step(step, pipeline.datamanager.next_train())
        kinds.append("D" if result.verdict is not None else "S" if result.skipped else "H")
        history.append(pipeline.model.gaussian_state())  # detached copies
    return pipeline, state, "".join(kinds), history


def assert_same_states(a: TrainingState, b: TrainingState) -> None:
    for name, value in a.model.gaussian_state().items():
        assert torch.equal(value, b.model.gaussian_state()[name]), name
    for name, opt in a.optimizers.items():
        (pa,), (pb,) = opt.param_groups[0]["params"], b.optimizers[name].param_groups[0]["params"]
        for key in ("exp_avg", "exp_avg_sq", "step"):
            assert torch.equal(opt.state[pa][key], b.optimizers[name].state[pb][key]), (name, key)
    for key, value in a.strategy_state.items():
        if isinstance(value, torch.Tensor):
            assert torch.equal(value, b.strategy_state[key]), key


@pytest.mark.parametrize("method", ["splatfacto", "kc-splatfacto", "splatfacto-mcmc"])
def test_good_steps_are_the_host_verdict_s_bit_for_bit(tmp_path, method):
    _, host, host_kinds, _ = train(tmp_path / "host", method, device_verdict=False)
    _, device, kinds, history = train(tmp_path / "device", method, device_verdict=True)
    assert set(host_kinds) == {"H"}
    # the device takes it on the steps without refinement, the host on the others (the count grew there)
    assert kinds.count("D") >= STEPS // 2 and "H" in kinds, kinds
    refining = [step for step in range(STEPS) if device.strategy.refines_at(step)]
    assert [step for step, kind in enumerate(kinds) if kind == "H"] == refining
    assert device.model.num_points != len(history[0]["means"])  # step 0 refines nothing
    assert_same_states(host, device)


@pytest.mark.parametrize("method", ["splatfacto", "kc-splatfacto"])
def test_a_bad_step_leaves_the_run_where_the_host_s_skip_leaves_it(tmp_path, method):
    _, host, host_kinds, _ = train(tmp_path / "host", method, device_verdict=False, bad_step=BAD_STEP)
    _, device, kinds, history = train(tmp_path / "device", method, device_verdict=True, bad_step=BAD_STEP)
    assert host_kinds[BAD_STEP] == "S" and kinds[BAD_STEP] == "D"
    for name, value in history[BAD_STEP].items():  # the bad step changed nothing
        assert torch.equal(value, history[BAD_STEP - 1][name]), name
    assert_same_states(host, device)  # and 24 steps later, with refinements between, the runs are one


def test_a_bad_step_on_the_device_leaves_mcmc_s_gaussians_as_they_were(tmp_path):
    # MCMC's noise is drawn (and multiplied by 0) where the host skips the draw: later steps differ in their noise,
    # so this strategy is held to the bad step itself
    pipeline, state, kinds, history = train(tmp_path, "splatfacto-mcmc", device_verdict=True, bad_step=BAD_STEP)
    assert kinds[BAD_STEP] == "D"
    for name, value in history[BAD_STEP].items():
        assert torch.equal(value, history[BAD_STEP - 1][name]), name
    assert all(torch.isfinite(p).all() for p in pipeline.model.gauss_params.values())


def test_the_verdict_read_later_says_what_the_host_says(tmp_path):
    pipeline, config = demo_pipeline(tmp_path, "splatfacto", seed=0)
    state = TrainingState(pipeline.model, config.optimizers, device_verdict=True)
    poison_loss_at(pipeline.model, {1})
    returned = []
    poisoned = pipeline.model.get_loss_dict
    pipeline.model.get_loss_dict = lambda outputs, batch: returned.append(poisoned(outputs, batch)) or returned[-1]
    good = state.step(0, pipeline.datamanager.next_train())
    bad = state.step(1, pipeline.datamanager.next_train())
    for term in returned[-1].values():  # as a CUDA graph's next replay writes into the buffers it returned
        term.detach().fill_(0.5)
    assert good.verdict.reason() is None
    assert bad.verdict.reason() == "non-finite loss (main_loss=nan)"
    assert bad.skipped is None and bad.losses  # the step ran; its update was not applied


@pytest.mark.parametrize("why", ["unfused Adam", "a strategy that refines at every step"])
def test_the_host_takes_the_verdict_where_the_device_cannot(tmp_path, why):
    if why == "unfused Adam":  # torch's per-tensor Adam has no found_inf
        _, _, kinds, _ = train(tmp_path, "splatfacto", device_verdict=True, fused=False)
    else:
        pipeline, config = demo_pipeline(tmp_path, "splatfacto", seed=0)
        strategy = config.pipeline.model.density_strategy(pipeline.model.num_train_data)

        class Busy:  # host work at every step: the device cannot take a verdict it would have to undo
            absgrad = strategy.absgrad

            def refines_at(self, step):
                return True

            def __getattr__(self, name):
                return getattr(strategy, name)

        state = TrainingState(pipeline.model, config.optimizers, strategy=Busy(), device_verdict=True)
        kinds = "".join("H" if state.step(s, pipeline.datamanager.next_train()).verdict is None else "D"
                        for s in range(4))
    assert "D" not in kinds


def test_a_strategy_without_the_interface_is_refused_by_name(tmp_path):
    pipeline, config = demo_pipeline(tmp_path, "splatfacto", seed=0)
    strategy = config.pipeline.model.density_strategy(pipeline.model.num_train_data)

    class GsplatOnly:  # gsplat's Strategy interface, without refines_at and cap
        absgrad = strategy.absgrad
        check_sanity = strategy.check_sanity
        initialize_state = strategy.initialize_state
        step_pre_backward = strategy.step_pre_backward
        step_post_backward = strategy.step_post_backward

    with pytest.raises(TypeError, match="GsplatOnly is not a density strategy: it lacks refines_at, cap"):
        TrainingState(pipeline.model, config.optimizers, strategy=GsplatOnly())


@pytest.mark.parametrize("device", [
    "cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA"))])
def test_the_trainer_skips_a_bad_update_on_the_device_and_reports_it_at_the_next_log(tmp_path, device):
    config = tiny_demo_config("splatfacto", tmp_path, iterations=12, steps_scale=1.0)  # no refinement in 12 steps
    config.machine.device = device
    if device == "cpu":
        config.machine.step_verdict = "device"  # CUDA's default ('auto')
    trainer = Trainer(config)
    trainer.setup()
    assert trainer.state.device_verdict
    poison_loss_at(trainer.model, {5})
    snapshots, waiting = {}, {}
    original = trainer.train_iteration

    def recording(step):
        snapshots[step] = trainer.model.gaussian_state()  # detached copies
        waiting[step] = len(trainer.state.verdicts.waiting)
        return original(step)

    trainer.train_iteration = recording
    with pytest.warns(RuntimeWarning, match="step 6: non-finite loss"):
        trainer.train()
    for name, value in snapshots[5].items():
        assert torch.equal(value, snapshots[6][name]), name  # the bad step changed nothing
    assert not torch.equal(snapshots[6]["means"], snapshots[7]["means"])  # the next one updates
    assert waiting[6] == 6 and waiting[10] == 0  # read at the log after step 10, not before
    bad = [r for r in read_metrics(trainer.run_dir / "metrics.jsonl") if r["kind"] == "bad_step"]
    assert [r["step"] for r in bad] == [6] and bad[0]["reason"].startswith("non-finite loss")
