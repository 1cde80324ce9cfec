"""The scene plan in a run (:mod:`kc_splatfacto.plan.scene_plan`): made from the training split before the model is
built, printed, written to the run folder and recorded in ``config.yml`` (the planned values); a resume applies the
run's ``plan.json`` again instead of measuring anew, so that it continues the same run."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import TYPE_CHECKING, Any

from kc_splatfacto.engine.checkpoints import CHECKPOINT_DIR
from kc_splatfacto.engine.datamanager import DataManager
from kc_splatfacto.engine.validation import validate_config
from kc_splatfacto.plan.scene_plan import (
    PLAN_FILE,
    ScenePlan,
    make_scene_plan,
    read_choices,
    reapply_choices,
    user_set_fields,
)
from kc_splatfacto.registry import discover_methods

if TYPE_CHECKING:
    from kc_splatfacto.engine.trainer import TrainerConfig


def plan_is_on(config: TrainerConfig) -> bool:
    return config.pipeline.model.plan == "on"


def method_default(config: TrainerConfig) -> Any | None:
    """The registered config of the run's method (what the user's settings are compared with), or None."""
    spec = discover_methods().get(config.method_name)
    return spec.config if spec is not None else None


def plan_scene(config: TrainerConfig, datamanager: DataManager) -> ScenePlan:
    """The plan of ``config`` for the scene ``datamanager`` loaded (its training split only)."""
    dataset = datamanager.train_dataset
    images = [dataset.image_uint8(i) for i in range(len(dataset))]
    seed = datamanager.seed_points()
    points = seed[0] if seed is not None else None
    return make_scene_plan(config, images, dataset.cameras, points, str(datamanager.dataparser_config.data),
                           user_set_fields(config, method_default(config)))


def recorded_plan_file(load_dir: Path) -> Path:
    """Where the run that ``--load-dir`` names (the run folder, its nerfstudio_models folder or a checkpoint in it)
    keeps its plan."""
    folder = Path(load_dir)
    if folder.is_file():
        folder = folder.parent
    if folder.name == CHECKPOINT_DIR:
        folder = folder.parent
    return folder / PLAN_FILE


def apply_recorded_plan(config: TrainerConfig) -> dict[str, Any]:
    """A resume with the plan on continues with the choices the run recorded where this command asks what the run
    asked (:func:`~kc_splatfacto.plan.scene_plan.reapply_choices`; in place; returns what it set, {} when the run has
    no plan.json)."""
    if config.load_dir is None or not plan_is_on(config):
        return {}
    path = recorded_plan_file(config.load_dir)
    if not path.is_file():
        return {}
    return reapply_choices(config, read_choices(path))


def plan_only(config: TrainerConfig) -> ScenePlan:
    """``kc-train METHOD --data SCENE --plan-only``: the plan the run would get, made from the scene's training split
    alone (no run folder, no model); with the plan off, the plan it would get with it on."""
    config = copy.deepcopy(config)
    validate_config(config)
    config.pipeline.model.plan = "on"
    dataparser = config.pipeline.datamanager.resolve_dataparser()
    datamanager = config.pipeline.datamanager.setup(seed=config.machine.seed, dataparser=dataparser)
    return plan_scene(config, datamanager)
