"""engine/training_state.py: the one owner of a training step. Checked against independent readings: gsplat
simple_trainer's step written out by hand (render, strategy hooks, loss, backward, Adam, schedules) must give the
same Gaussians bit for bit; the step's schedules; the visible Gaussians counted from the render's radii; a skipped
step leaves every parameter as it was; and, on the source, that the step's calls have one owner."""

from __future__ import annotations

import ast
import io
from pathlib import Path

import pytest
import torch

from kc_splatfacto.engine.training_state import PARAMETER_SCAN_EVERY, StepHooks, TrainingState
from kc_splatfacto.model.mcmc import GaussianCapError, MCMCStrategy
from kc_splatfacto.model.strategy import DefaultStrategy
from tests.training_utils import demo_pipeline

PACKAGE = Path(__file__).resolve().parents[2] / "kc_splatfacto"


def make_state(tmp_path, method="kc-splatfacto", seed=0, strategy=None, **overrides):
    pipeline, config = demo_pipeline(tmp_path, method, seed, **overrides)
    return pipeline, TrainingState(pipeline.model, config.optimizers, strategy=strategy)


class RecordingStrategy(DefaultStrategy):
    """The default strategy, keeping the ``info`` each post-backward call read."""

    infos: list

    def step_post_backward(self, params, optimizers, state, step, info, lr, noise_factor=None):
        self.infos.append(info)
        return super().step_post_backward(params, optimizers, state, step, info, lr, noise_factor)


def test_the_step_sets_the_model_s_step_and_what_the_schedules_read(tmp_path):
    pipeline, state = make_state(tmp_path)
    model, schedule = pipeline.model, pipeline.model.schedule
    for step in (0, schedule.resolution_schedule, 10 * schedule.resolution_schedule):
        batch = pipeline.datamanager.next_train()
        result = state.step(step, batch)
        assert model.step == step
        expected = 2 ** max(model.config.num_downscales - step // schedule.resolution_schedule, 0)
        image_h, image_w = batch["image"].shape[:2]
        assert tuple(result.outputs["rgb"].shape[:2]) == (image_h // expected, image_w // expected)
        assert model.schedule_state() == {"sh_degree": min(step // schedule.sh_degree_interval, model.sh_degree),
                                          "train_downscale": expected}


def test_density_control_reads_the_step_s_own_render_and_the_render_s_info_stays_inside(tmp_path):
    pipeline, config = demo_pipeline(tmp_path)
    strategy = RecordingStrategy(**{f: getattr(config.pipeline.model.density_strategy(pipeline.model.num_train_data),
                                               f) for f in DefaultStrategy.__dataclass_fields__})
    strategy.infos = []
    state = TrainingState(pipeline.model, config.optimizers, strategy=strategy)
    result = state.step(1, pipeline.datamanager.next_train())  # past step 0, before the warm-up: statistics only
    assert result.skipped is None and not any(result.density.values())
    assert "info" not in result.outputs
    (info,) = strategy.infos
    assert info["means2d"].grad is not None  # the pre-backward hook kept the projected means' gradient
    visible = (info["radii"] > 0).all(dim=-1).reshape(-1).float()  # the Gaussians this view saw
    torch.testing.assert_close(state.strategy_state["count"].reshape(-1), visible, rtol=0, atol=0)


def _gsplat_style_steps(pipeline, config, steps: int) -> None:
    """gsplat simple_trainer's training step written out, on our model and strategy: the oracle of the state."""
    model = pipeline.model
    strategy = config.pipeline.model.density_strategy(model.num_train_data)
    strategy_state = strategy.initialize_state(scene_scale=model.scene_scale)
    optimizers, schedulers = config.optimizers.setup(model.parameter_groups(),
                                                     steps_scale=config.pipeline.model.steps_scale)
    for step in range(steps):
        model.set_step(step)
        batch = pipeline.datamanager.next_train()
        outputs = model.get_outputs(batch["camera"], absgrad=strategy.absgrad)
        strategy.step_pre_backward(model.gauss_params, optimizers, strategy_state, step, outputs["info"])
        loss = sum(model.get_loss_dict(outputs, batch).values())
        loss.backward()
        for optimizer in optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        for scheduler in schedulers.values():
            scheduler.step()
        strategy.step_post_backward(model.gauss_params, optimizers, strategy_state, step, outputs["info"])


@pytest.mark.parametrize("method", ["splatfacto", "kc-splatfacto"])
def test_steps_of_the_state_equal_gsplat_simple_trainer_s_step_written_by_hand(tmp_path, method):
    steps = 24  # past the compressed warm-up (10 steps), refining every 2: a low threshold makes Gaussians grow
    pipeline, state = make_state(tmp_path / "state", method, seed=4, densify_grad_thresh=1e-7)
    counts = {}
    for step in range(steps):
        result = state.step(step, pipeline.datamanager.next_train())
        assert result.skipped is None
        for key, value in result.density.items():
            counts[key] = counts.get(key, 0) + value
    assert counts.get("duplicated", 0) + counts.get("split", 0) > 0  # density control did change the count
    by_hand, config = demo_pipeline(tmp_path / "hand", method, seed=4, densify_grad_thresh=1e-7)
    _gsplat_style_steps(by_hand, config, steps)
    for name, value in pipeline.model.gaussian_state().items():
        assert torch.equal(value, by_hand.model.gaussian_state()[name]), name


def test_hooks_see_every_phase_in_order_and_the_loss_before_backward(tmp_path):
    pipeline, state = make_state(tmp_path)
    seen = []

    def inspect(loss_dict, image, loss):
        assert state.model.means.grad is None  # before backward
        torch.testing.assert_close(loss, torch.stack(list(loss_dict.values())).sum())
        seen.append(("loss", tuple(image.shape)))

    result = state.step(1, pipeline.datamanager.next_train(), StepHooks(lap=seen.append, inspect_loss=inspect))
    phases = ["render", "losses", ("loss", tuple(result.outputs["rgb"].shape)), "backward", "optimizer",
              "density_control"]
    assert seen == phases
    seen.clear()
    state.step(PARAMETER_SCAN_EVERY, pipeline.datamanager.next_train(), StepHooks(lap=seen.append,
                                                                                 inspect_loss=inspect))
    assert seen == ["optimizer", *phases]  # the parameter scan first, timed with the optimizer's phase


def test_a_non_finite_loss_skips_the_update_but_not_the_schedules(tmp_path):
    pipeline, state = make_state(tmp_path, "splatfacto")
    before = pipeline.model.gaussian_state()
    rates = [opt.param_groups[0]["lr"] for opt in state.optimizers.values()]
    state.model.get_loss_dict = lambda outputs, batch: {"main_loss": outputs["rgb"].sum() * float("nan")}
    result = state.step(0, pipeline.datamanager.next_train())
    assert result.skipped is not None and result.skipped.startswith("non-finite loss")
    assert result.density == {}
    for name, value in pipeline.model.gaussian_state().items():
        assert torch.equal(value, before[name]), name
    assert all(p.grad is None for p in pipeline.model.gauss_params.values())
    assert state.schedulers["means"].last_epoch == 1
    assert [opt.param_groups[0]["lr"] for opt in state.optimizers.values()][1:] == rates[1:]  # unscheduled groups


def test_non_finite_gaussians_are_removed_with_their_optimizer_rows_and_statistics(tmp_path):
    pipeline, state = make_state(tmp_path, "splatfacto")
    for step in range(2):
        state.step(step, pipeline.datamanager.next_train())
    n = pipeline.model.num_points
    with torch.no_grad():
        pipeline.model.gauss_params["opacities"][[3, 7]] = float("inf")
    assert state.remove_non_finite_gaussians() == 2
    assert pipeline.model.num_points == n - 2
    assert state.optimizers["opacities"].state[pipeline.model.opacities]["exp_avg"].shape[0] == n - 2
    assert state.strategy_state["count"].shape[0] == n - 2


def test_the_mcmc_strategy_is_built_from_the_config_and_refuses_a_cap_below_the_seed_points(tmp_path):
    _, state = make_state(tmp_path / "a", "splatfacto-mcmc")
    assert isinstance(state.strategy, MCMCStrategy)
    pipeline, config = demo_pipeline(tmp_path / "b", "splatfacto-mcmc", max_gs_num=10)
    with pytest.raises(GaussianCapError, match="max_gs_num \\(10\\) is smaller"):
        TrainingState(pipeline.model, config.optimizers)


def test_state_dict_round_trip_continues_bit_for_bit(tmp_path):
    pipeline, state = make_state(tmp_path / "a", "splatfacto", seed=1)
    for step in range(6):
        state.step(step, pipeline.datamanager.next_train())
    buffer = io.BytesIO()
    torch.save({**pipeline.state_dict(), **state.state_dict()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=False)
    restored_pipeline, restored = make_state(tmp_path / "b", "splatfacto", seed=2)
    restored_pipeline.load_state_dict(saved, step=6)
    restored.load_state_dict(saved)
    rng = torch.get_rng_state()
    for step in range(6, 9):
        state.step(step, pipeline.datamanager.next_train())
    torch.set_rng_state(rng)
    for step in range(6, 9):
        restored.step(step, restored_pipeline.datamanager.next_train())
    for name, value in pipeline.model.gaussian_state().items():
        assert torch.equal(value, restored_pipeline.model.gaussian_state()[name]), name


def _calls(exclude: tuple[str, ...]):
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE).as_posix()
        if relative.startswith(exclude):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                yield relative, node.func.attr, ast.unparse(node.func.value)


def test_the_step_s_calls_have_one_owner():
    # the nerfstudio plugin's model is nerfstudio's SplatfactoModel, which takes its own steps
    owners = {}
    for name, attr, target in _calls(("nerfstudio_plugin/",)):
        if attr in ("step_pre_backward", "step_post_backward", "backward", "zero_grad") or (
                attr == "step" and target in ("optimizer", "scheduler")):
            owners.setdefault(attr, set()).add(name)
    # the strategies delegate among themselves; everything else is the training state's
    outside = {attr: names - {"engine/training_state.py", "model/strategy.py", "model/mcmc.py"}
               for attr, names in owners.items()}
    assert {attr: names for attr, names in outside.items() if names} == {}
    assert {"step_pre_backward", "step_post_backward", "backward", "step"} <= set(owners)


class _Verdict:
    """A device verdict read as ``reason()`` (None: good)."""

    def __init__(self, reason):
        self._reason = reason

    def reason(self):
        return self._reason


def test_verdicts_come_out_in_step_order_and_count_bad_steps_in_a_row():
    from kc_splatfacto.engine.training_state import BadStep, StepVerdicts

    verdicts = StepVerdicts()
    verdicts.wait(1, _Verdict("non-finite loss"))
    verdicts.wait(2, _Verdict("non-finite render"))
    # a host verdict reads those waiting first: steps 1 and 2, then its own 3
    assert verdicts.host(3, "non-finite parameters") == [BadStep(1, "non-finite loss", 1),
                                                        BadStep(2, "non-finite render", 2),
                                                        BadStep(3, "non-finite parameters", 3)]
    verdicts.wait(4, _Verdict(None))  # a good step ends the row
    verdicts.wait(5, _Verdict("non-finite loss"))
    assert verdicts.read() == [BadStep(5, "non-finite loss", 1)] and verdicts.waiting == []
    assert verdicts.host(6, None) == [] and verdicts.bad_in_a_row == 0
