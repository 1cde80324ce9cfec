"""The scene plan in ``ns-train`` (docs/plan.md): kc-train's rules (:mod:`kc_splatfacto.plan.scene_plan`) on the
training split nerfstudio's dataparser gives, applied to nerfstudio's ``TrainerConfig`` before its pipeline is built.

:class:`~.configs.PlanningTrainer` is nerfstudio's ``Trainer`` whose ``setup`` first makes the plan (the model config's
``plan`` on; ``--pipeline.model.plan off``: the fixed settings, nerfstudio's own trainer then), prints its table,
writes ``plan.json`` to the run folder and writes ``config.yml`` again with the planned values (nerfstudio writes it
before the trainer starts), so ``ns-eval``, ``ns-render`` and ``ns-export`` rebuild the model the run trained. A run
continued with ``--load-dir`` takes the plan its first run recorded (that run's ``plan.json``) instead of measuring
anew, as kc-train does.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import torch
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.engine.trainer import TrainerConfig

from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.engine.scene_planning import apply_recorded_plan, plan_is_on, recorded_plan_file
from kc_splatfacto.nerfstudio_plugin.cpu import viewmats_from_camera_to_worlds
from kc_splatfacto.plan.scene_plan import (
    PLAN_FILE,
    ScenePlan,
    apply_choices,
    make_scene_plan,
    user_set_fields,
)


def project_cameras(cameras: Any) -> Cameras:
    """nerfstudio's ``Cameras`` (OpenGL camera-to-worlds, fx, fy, cx, cy) as the project's pinhole ``Cameras``."""
    count = cameras.camera_to_worlds.shape[0]
    Ks = torch.zeros(count, 3, 3)
    Ks[:, 0, 0], Ks[:, 1, 1] = cameras.fx.reshape(-1), cameras.fy.reshape(-1)
    Ks[:, 0, 2], Ks[:, 1, 2] = cameras.cx.reshape(-1), cameras.cy.reshape(-1)
    Ks[:, 2, 2] = 1.0
    return Cameras(viewmats_from_camera_to_worlds(cameras.camera_to_worlds.float().cpu()), Ks,
                   cameras.width.reshape(-1).long().cpu(), cameras.height.reshape(-1).long().cpu())


def training_split(config: TrainerConfig) -> tuple[list[torch.Tensor], Cameras, torch.Tensor | None, str]:
    """(images [H, W, C] uint8, cameras, seed points [M, 3] or None, the scene) of ``config``'s training split, as
    nerfstudio's data manager will load it (its dataparser, its ``data``, its camera resolution scale)."""
    manager = config.pipeline.datamanager
    parser_config = copy.deepcopy(manager.dataparser)
    if getattr(manager, "data", None) is not None:
        parser_config.data = Path(manager.data)
    outputs = parser_config.setup().get_dataparser_outputs(split="train")
    dataset = InputDataset(outputs, scale_factor=getattr(manager, "camera_res_scale_factor", 1.0))
    images = [torch.from_numpy(dataset.get_numpy_image(i)) for i in range(len(dataset))]
    points = outputs.metadata.get("points3D_xyz")
    return images, project_cameras(dataset.cameras), points, str(parser_config.data)


def plan_nerfstudio_run(config: TrainerConfig, method_default: Any | None) -> ScenePlan | dict[str, Any] | None:
    """Make (or, for ``--load-dir``, read again) the run's plan and apply it to ``config`` in place: the plan, the
    choices a continued run applied again, or None with the plan off. ``method_default``: the registered config of
    the run's method, what the user's settings are compared with (None: every field the plan's)."""
    if not plan_is_on(config):
        return None
    if config.load_dir is not None:  # kc-train's resume: the recorded choices where this command asks what it asked
        return apply_recorded_plan(config)
    images, cameras, points, scene = training_split(config)
    plan = make_scene_plan(config, images, cameras, points, scene, user_set_fields(config, method_default))
    apply_choices(config, plan.choices())
    return plan


def start_planned_run(config: TrainerConfig, base_dir: Path, method_default: Any | None) -> None:
    """What the plugin's trainer does before it builds the pipeline: the plan made (or read again) and applied to
    ``config``, its table printed, ``plan.json`` written to the run folder ``base_dir`` and ``config.yml`` written
    again with the planned values; nothing with the plan off."""
    plan = plan_nerfstudio_run(config, method_default)
    if plan is None:
        return
    base_dir.mkdir(parents=True, exist_ok=True)
    if isinstance(plan, ScenePlan):
        print(plan.table(), flush=True)
        plan.write(base_dir)
    else:
        recorded = recorded_plan_file(Path(config.load_dir))
        if recorded.is_file():
            (base_dir / PLAN_FILE).write_text(recorded.read_text())
            print(f"scene plan: the choices {recorded} recorded, applied again: {', '.join(plan) or 'none'}",
                  flush=True)
    config.save_config()  # nerfstudio wrote config.yml before the trainer started
