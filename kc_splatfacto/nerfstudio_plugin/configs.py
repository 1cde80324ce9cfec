"""The plugin's methods as nerfstudio ``TrainerConfig``s: nerfstudio 1.1.5's ``splatfacto`` settings (steps, optimizers,
data manager, viewer) with :class:`~.model.KCSplatfactoModelConfig`, one method for each of the project's
(``method_configs/splatfacto_configs.py``: each method's settings are defined there once and read from there).

Names are ``kc-train``'s, except the project's plain ``splatfacto``, which nerfstudio already has: here it is
``splatfacto-cpu`` (nerfstudio's Splatfacto that also trains without CUDA).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, Literal, Type

import torch
from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanagerConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
from nerfstudio.engine import schedulers
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from kc_splatfacto.nerfstudio_plugin.model import KCSplatfactoModelConfig
from kc_splatfacto.nerfstudio_plugin.plan import start_planned_run

CARRIED = ("frequency", "plan", "plan_skip")
"""model fields every method carries into nerfstudio as the project's method sets them, whatever its splatfacto's"""
PLAIN_SPLATFACTO = "splatfacto-cpu"
"""the nerfstudio name of the project's ``splatfacto`` (the frequency-loss weights 0)"""


class ExponentialDecayScheduler(schedulers.ExponentialDecayScheduler):
    """nerfstudio's, giving the same learning rates as Python floats instead of numpy.float64: nerfstudio's end up in
    the checkpoint (the optimizer's and the scheduler's state), which torch >= 2.6's ``torch.load`` (weights only, in
    ``ns-eval``, ``ns-viewer``, ``ns-export``, ``ns-render`` and ``--load-dir``) refuses to read."""

    def get_scheduler(self, optimizer: torch.optim.Optimizer, lr_init: float) -> torch.optim.lr_scheduler.LRScheduler:
        # nerfstudio's decay function, taken from the scheduler it builds (on a stand-in optimizer, whose learning
        # rate that scheduler sets)
        stand_in = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=lr_init)
        decay = super().get_scheduler(stand_in, lr_init).lr_lambdas[0]
        return torch.optim.lr_scheduler.LambdaLR(optimizer, lr_lambda=lambda step: float(decay(step)))


@dataclass
class ExponentialDecaySchedulerConfig(schedulers.ExponentialDecaySchedulerConfig):
    """nerfstudio's exponential decay with warm-up, its learning rates as Python floats
    (:class:`ExponentialDecayScheduler`)."""

    _target: Type = field(default_factory=lambda: ExponentialDecayScheduler)


class PlanningTrainer(Trainer):
    """nerfstudio's ``Trainer`` that makes the scene plan (:mod:`.plan`) before it builds the pipeline, against the
    plugin's registered config of the run's method (what the user set wins)."""

    def setup(self, test_mode: Literal["test", "val", "inference"] = "val") -> None:
        if self.local_rank == 0:
            spec = method_specifications().get(self.config.method_name)
            start_planned_run(self.config, Path(self.base_dir), spec.config if spec is not None else None)
        super().setup(test_mode)


@dataclass
class PlanningTrainerConfig(TrainerConfig):
    """nerfstudio's ``TrainerConfig`` whose trainer makes the scene plan (:class:`PlanningTrainer`)."""

    _target: Type = field(default_factory=lambda: PlanningTrainer)


def splatfacto_trainer(method_name: str, model: KCSplatfactoModelConfig) -> PlanningTrainerConfig:
    """nerfstudio 1.1.5's ``method_configs["splatfacto"]`` with ``model`` and ``method_name`` (the test suite compares
    the two field by field with nerfstudio installed), its trainer the one that makes the scene plan."""
    return PlanningTrainerConfig(
        method_name=method_name,
        steps_per_eval_image=100,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=1000,
        max_num_iterations=30000,
        mixed_precision=False,
        pipeline=VanillaPipelineConfig(
            datamanager=FullImageDatamanagerConfig(
                dataparser=NerfstudioDataParserConfig(load_3D_points=True),
                cache_images_type="uint8",
            ),
            model=model,
        ),
        optimizers={
            "means": {
                "optimizer": AdamOptimizerConfig(lr=1.6e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1.6e-6, max_steps=30000),
            },
            "features_dc": {"optimizer": AdamOptimizerConfig(lr=0.0025, eps=1e-15), "scheduler": None},
            "features_rest": {"optimizer": AdamOptimizerConfig(lr=0.0025 / 20, eps=1e-15), "scheduler": None},
            "opacities": {"optimizer": AdamOptimizerConfig(lr=0.05, eps=1e-15), "scheduler": None},
            "scales": {"optimizer": AdamOptimizerConfig(lr=0.005, eps=1e-15), "scheduler": None},
            "quats": {"optimizer": AdamOptimizerConfig(lr=0.001, eps=1e-15), "scheduler": None},
            "camera_opt": {
                "optimizer": AdamOptimizerConfig(lr=1e-4, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=5e-7, max_steps=30000, warmup_steps=1000,
                                                             lr_pre_warmup=0),
            },
            "bilateral_grid": {
                "optimizer": AdamOptimizerConfig(lr=2e-3, eps=1e-15),
                "scheduler": ExponentialDecaySchedulerConfig(lr_final=1e-4, max_steps=30000, warmup_steps=1000,
                                                             lr_pre_warmup=0),
            },
        },
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )


def nerfstudio_model_config(project_model: Any, project_baseline: Any) -> KCSplatfactoModelConfig:
    """The plugin's model config for one of the project's methods: the frequency-loss and scene-plan settings
    (:data:`CARRIED`) of ``project_model`` (the project's model config), and each other field in which it differs
    from the project's ``splatfacto`` (``project_baseline``, whose fields are nerfstudio's defaults). A field
    nerfstudio's Splatfacto does not have is an error: that method cannot be the same method in nerfstudio."""
    ours = {field.name: getattr(project_model, field.name) for field in dataclasses.fields(project_model)}
    baseline = {field.name: getattr(project_baseline, field.name) for field in dataclasses.fields(project_baseline)}
    changes = {name: value for name, value in ours.items() if name in CARRIED or value != baseline[name]}
    changes["frequency"] = dataclasses.replace(changes["frequency"])  # the plugin's own copy
    known = {field.name for field in dataclasses.fields(KCSplatfactoModelConfig)}
    foreign = sorted(set(changes) - known)
    if foreign:
        raise ValueError(f"the project's method sets {foreign}, which nerfstudio's Splatfacto has no field for")
    return KCSplatfactoModelConfig(**changes)


def method_specifications(project_methods: ModuleType | None = None) -> dict[str, MethodSpecification]:
    """{nerfstudio method name: its MethodSpecification}, one for each MethodSpecification of the project's
    ``method_configs.splatfacto_configs`` (or ``project_methods``, a module holding such specifications)."""
    if project_methods is None:
        from method_configs import splatfacto_configs as project_methods
    specs = [value for value in vars(project_methods).values() if type(value).__name__ == "MethodSpecification"]
    by_name = {spec.config.method_name: spec for spec in specs}
    baseline = by_name["splatfacto"].config.pipeline.model
    result = {}
    for name, spec in by_name.items():
        ns_name = PLAIN_SPLATFACTO if name == "splatfacto" else name
        model = nerfstudio_model_config(spec.config.pipeline.model, baseline)
        result[ns_name] = MethodSpecification(config=splatfacto_trainer(ns_name, model),
                                              description=f"[kc-splatfacto] {spec.description}")
    return result
