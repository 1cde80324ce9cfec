"""engine/pipeline.py: a training step's three calls (train_view, train_losses, after_optimizer_step) and the state
they own. The step is set in one place and density control reads what rendering produced; checked against
independent readings: the step's schedules, the visible Gaussians counted from the render's radii, a torch.save round
trip of the state. And, on the source, that no module outside the model touches its tensors or sets its step."""

from __future__ import annotations

import ast
import io
from pathlib import Path

import pytest
import torch

from kc_splatfacto.engine.pipeline import Pipeline
from tests.training_utils import tiny_demo_config

PACKAGE = Path(__file__).resolve().parents[2] / "kc_splatfacto"


def make_pipeline(tmp_path, method="kc-splatfacto", seed=0) -> Pipeline:
    config = tiny_demo_config(method, tmp_path)
    config.pipeline.datamanager.dataparser.demo_cache_dir = tmp_path / "demo-cache"
    torch.manual_seed(seed)
    return config.pipeline.setup(seed=seed, dataparser=config.pipeline.datamanager.resolve_dataparser())


def one_step(pipeline: Pipeline, step: int, optimizers=None):
    outputs, batch = pipeline.train_view(step)
    losses = pipeline.train_losses(outputs, batch)
    torch.stack(list(losses.values())).sum().backward()
    optimizers = optimizers if optimizers is not None else {}
    report = pipeline.after_optimizer_step(outputs, optimizers)
    return outputs, batch, losses, report


def test_train_view_sets_the_step_and_what_the_schedules_read(tmp_path):
    pipeline = make_pipeline(tmp_path)
    model = pipeline.model
    schedule = model.schedule
    for step in (0, schedule.resolution_schedule, 10 * schedule.resolution_schedule):
        outputs, batch = pipeline.train_view(step)
        assert model.step == step
        # the render's size follows the step's resolution (2^num_downscales at first, halved every interval)
        expected = 2 ** max(model.config.num_downscales - step // schedule.resolution_schedule, 0)
        image_h, image_w = batch["image"].shape[:2]
        assert tuple(outputs["rgb"].shape[:2]) == (image_h // expected, image_w // expected)
        assert model.schedule_state() == {"sh_degree": min(step // schedule.sh_degree_interval, model.sh_degree),
                                          "train_downscale": expected}


def test_density_control_reads_the_step_s_render_counted_independently(tmp_path):
    pipeline = make_pipeline(tmp_path)
    state = pipeline.model.strategy_state
    before = state["count"].clone() if state.get("count") is not None else None
    outputs, _, _, report = one_step(pipeline, 1)  # past step 0, before the warm-up's end: statistics only
    assert not any(report.values())
    means2d = outputs["info"]["means2d"]
    assert means2d.grad is not None  # before_backward kept the projected means' gradient for density control
    visible = (outputs["info"]["radii"] > 0).all(dim=-1).reshape(-1).float()  # the Gaussians this view saw
    counted = state["count"] - (before if before is not None else 0)
    torch.testing.assert_close(counted.reshape(-1), visible, rtol=0, atol=0)


def test_get_train_loss_dict_is_train_view_then_train_losses(tmp_path):
    values = []
    for split in (False, True):
        pipeline = make_pipeline(tmp_path / str(split), seed=3)
        torch.manual_seed(5)
        if split:
            outputs, batch = pipeline.train_view(0)
            losses = pipeline.train_losses(outputs, batch)
        else:
            outputs, losses, batch = pipeline.get_train_loss_dict(0)
        values.append(({k: float(v) for k, v in losses.items()}, int(batch["image_idx"])))
    assert values[0] == values[1] and set(values[0][0]) >= {"main_loss", "wavelet_loss", "kc_loss", "cbc_loss"}


def test_state_dict_round_trip_through_a_weights_only_load_restores_gaussians_order_and_step(tmp_path):
    pipeline = make_pipeline(tmp_path / "a", seed=1)
    for step in range(3):
        one_step(pipeline, step)
    buffer = io.BytesIO()
    torch.save(pipeline.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)
    restored = make_pipeline(tmp_path / "b", seed=2)  # another seed: another image order until it is restored
    restored.load_state_dict(state, step=3)
    assert restored.model.step == 3
    for name, value in pipeline.model.gaussian_state().items():
        assert torch.equal(value, restored.model.gaussian_state()[name]), name
    upcoming = [pipeline.datamanager.next_train()["image_idx"] for _ in range(8)]
    assert [restored.datamanager.next_train()["image_idx"] for _ in range(8)] == upcoming


def _python_files(exclude: tuple[str, ...]):
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE).as_posix()
        if not relative.startswith(exclude):
            yield relative, ast.parse(path.read_text())


def test_no_module_outside_the_model_touches_its_tensors():
    # the nerfstudio plugin's model is nerfstudio's SplatfactoModel, whose gauss_params are its own API
    found = [f"{name}:{node.lineno}" for name, tree in _python_files(("model/", "nerfstudio_plugin/"))
             for node in ast.walk(tree) if isinstance(node, ast.Attribute) and node.attr == "gauss_params"]
    assert found == []


def test_the_model_step_has_one_writer():
    writers = []
    for name, tree in _python_files(("nerfstudio_plugin/",)):
        for node in ast.walk(tree):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
                node, (ast.AugAssign, ast.AnnAssign)) else []
            for target in targets:
                if isinstance(target, ast.Attribute) and target.attr == "step":
                    writers.append((name, ast.unparse(target.value), node.lineno))
    model_writers = [w for w in writers if w[0] == "model/splatfacto.py"]
    assert len(model_writers) == 2  # the initial 0 in __init__, and set_step
    others = [w for w in writers if w[0] != "model/splatfacto.py"]
    assert all(name == "viewer/viewer.py" and owner == "self" for name, owner, _ in others), others  # its own step


@pytest.mark.parametrize("method", ["splatfacto", "kc-splatfacto"])
def test_a_step_through_the_pipeline_equals_the_trainers(tmp_path, method):
    """The trainer takes its step through these calls: its first step's losses equal a step taken here by hand."""
    from kc_splatfacto.engine.trainer import Trainer

    config = tiny_demo_config(method, tmp_path / "trainer", iterations=1)
    config.pipeline.datamanager.dataparser.demo_cache_dir = tmp_path / "demo-cache"
    trainer = Trainer(config)
    trainer.setup()
    losses = dict(trainer.train_iteration(0))
    by_hand_config = tiny_demo_config(method, tmp_path / "hand", iterations=1)
    by_hand_config.pipeline.datamanager.dataparser.demo_cache_dir = tmp_path / "demo-cache"
    by_hand_config.machine.seed_everything()
    pipeline = by_hand_config.pipeline.setup(seed=by_hand_config.machine.seed,
                                            dataparser=by_hand_config.pipeline.datamanager.resolve_dataparser())
    _, _, by_hand, _ = one_step(pipeline, 0)
    assert {k: v for k, v in losses.items() if k != "loss"} == {k: float(v) for k, v in by_hand.items()}
