"""engine/pipeline.py: the scene's data and model, and their part of a checkpoint, checked by a torch.save round
trip; the trainer's step (the training state's, on the data manager's next view) against one taken by hand. And, on
the source, that no module outside the model and the training state touches its tensors or sets its step."""

from __future__ import annotations

import ast
import io
from pathlib import Path

import pytest
import torch

from kc_splatfacto.engine.optimizers import OptimizersConfig
from kc_splatfacto.engine.pipeline import Pipeline
from kc_splatfacto.engine.training_state import TrainingState
from tests.training_utils import demo_pipeline, tiny_demo_config

PACKAGE = Path(__file__).resolve().parents[2] / "kc_splatfacto"


def one_step(pipeline: Pipeline, state: TrainingState, step: int):
    return state.step(step, pipeline.datamanager.next_train())


def test_state_dict_round_trip_through_a_weights_only_load_restores_gaussians_order_and_step(tmp_path):
    pipeline, _ = demo_pipeline(tmp_path / "a", seed=1)
    state = TrainingState(pipeline.model, OptimizersConfig())
    for step in range(3):
        one_step(pipeline, state, step)
    buffer = io.BytesIO()
    torch.save(pipeline.state_dict(), buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=True)
    restored, _ = demo_pipeline(tmp_path / "b", seed=2)  # another seed: another image order until it is restored
    restored.load_state_dict(saved, step=3)
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


def test_no_module_outside_the_model_and_the_training_state_touches_its_tensors():
    # the nerfstudio plugin's model is nerfstudio's SplatfactoModel, whose gauss_params are its own API; the training
    # state hands them to density control
    found = [f"{name}:{node.lineno}" for name, tree in _python_files(("model/", "nerfstudio_plugin/",
                                                                     "engine/training_state.py"))
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
def test_the_trainer_s_step_equals_the_training_state_s_on_the_next_view(tmp_path, method):
    """The trainer's first step's losses equal a step of a training state on the pipeline's next view."""
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
    pipeline.model.train()
    by_hand = one_step(pipeline, TrainingState(pipeline.model, by_hand_config.optimizers), 0).losses
    assert {k: v for k, v in losses.items() if k != "loss"} == {k: float(v) for k, v in by_hand.items()}
