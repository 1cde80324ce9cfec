"""Logging backends beside ``metrics.jsonl``: tensorboard event files and an offline wandb run.

Each is a :class:`~kc_splatfacto.engine.callbacks.RecordSink`: it receives the records the trainer writes to
``metrics.jsonl`` and turns them into the backend's scalars, so the two never disagree and the JSON log stays the
record. Scalar names are ``<kind>/<field>`` (``train/main_loss``, ``eval/psnr``, ``densify/split``); lists of
numbers (per-band kurtosis) become ``<kind>/<field>/<i>``. Added on top: ``train/step_time_s`` (training seconds per
step between two train records) and, at each evaluation, the first ``LoggingConfig.eval_images`` eval views' render
beside their ground truth (``eval/view_<i>``). The packages are optional extras, imported when asked for.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import torch

from kc_splatfacto.engine.base_config import LoggingConfig
from kc_splatfacto.engine.callbacks import RecordSink
from kc_splatfacto.errors import import_optional

#: record fields that are bookkeeping, not curves
SKIPPED_FIELDS = frozenset({"kind", "step", "split", "path", "reason", "lpips_net", "lpips_unavailable", "per_image",
                            "per_image_psnr", "reference", "ssim_convention"})
#: the clocks every record carries: curves of the train records only (elsewhere they repeat them)
CLOCK_FIELDS = frozenset({"elapsed_s", "train_s", "train_cpu_s"})
INSTALL_HINT = {"tensorboard": "pip install 'kc-splatfacto[tensorboard]'", "wandb": "pip install 'kc-splatfacto[wandb]'"}


def import_backend(module: str, package: str, flag: str) -> Any:
    """``module`` imported for ``flag``; a one-line :class:`UserError` when ``package`` is missing or broken."""
    return import_optional(module, package, flag, INSTALL_HINT[package])


def flatten_record(record: dict[str, Any]) -> dict[str, float]:
    """``{"<kind>/<field>": value}`` of every finite number in ``record`` (lists element-wise, nested dicts by key;
    booleans, bookkeeping fields and, outside train records, the clocks left out)."""
    kind = record.get("kind", "record")
    scalars: dict[str, float] = {}

    def add(name: str, value: Any) -> None:
        if isinstance(value, bool) or value is None:
            return
        if isinstance(value, (int, float)):
            if math.isfinite(value):
                scalars[name] = float(value)
        elif isinstance(value, (list, tuple)):
            for i, item in enumerate(value):
                add(f"{name}/{i}", item)
        elif isinstance(value, dict):
            for key, item in value.items():
                add(f"{name}/{key}", item)

    for key, value in record.items():
        if key not in SKIPPED_FIELDS and (kind == "train" or key not in CLOCK_FIELDS):
            add(f"{kind}/{key}", value)
    return scalars


class _StepTime:
    """Training seconds per step between consecutive train records (``train_s`` excludes eval and checkpoints)."""

    def __init__(self) -> None:
        self._last: tuple[int, float] | None = None

    def __call__(self, record: dict[str, Any]) -> float | None:
        if record.get("kind") != "train" or "train_s" not in record:
            return None
        step, train_s = int(record["step"]), float(record["train_s"])
        previous, self._last = self._last, (step, train_s)
        if previous is None or step <= previous[0]:
            return None
        return (train_s - previous[1]) / (step - previous[0])


def eval_view_images(model, dataset, count: int) -> list[torch.Tensor]:
    """[3, H, 2W] float images in [0, 1]: render beside ground truth of the first ``count`` views of ``dataset``
    (rendered as the evaluation renders them: eval mode, no gradients, the mask applied)."""
    images = []
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            for index in range(min(count, len(dataset))):
                outputs = model.get_outputs(dataset.cameras[index])
                _, (pred, gt) = model.get_image_metrics(outputs, dataset[index])
                images.append(torch.cat([pred[0], gt[0].to(pred.dtype)], dim=-1).clamp(0, 1).cpu())
    finally:
        model.train(was_training)
    return images


class TensorboardSink(RecordSink):
    """Tensorboard event files in ``log_dir`` (torch's ``SummaryWriter``)."""

    def __init__(self, log_dir: Path, pipeline=None, eval_images: int = 1):
        tensorboard = import_backend("torch.utils.tensorboard", "tensorboard", "--logging.tensorboard")
        self.writer = tensorboard.SummaryWriter(log_dir=str(log_dir))
        self.pipeline, self.eval_images = pipeline, eval_images
        self._step_time = _StepTime()

    def write(self, record: dict[str, Any]) -> None:
        step = int(record.get("step", 0))
        for name, value in flatten_record(record).items():
            self.writer.add_scalar(name, value, step)
        step_time = self._step_time(record)
        if step_time is not None:
            self.writer.add_scalar("train/step_time_s", step_time, step)
        if record.get("kind") == "eval" and self.pipeline is not None and self.eval_images > 0:
            for i, image in enumerate(eval_view_images(self.pipeline.model, self.pipeline.datamanager.eval_dataset,
                                                       self.eval_images)):
                self.writer.add_image(f"eval/view_{i}", image, step)
        self.writer.flush()

    def close(self) -> None:
        self.writer.close()


def _plain(value: Any) -> Any:
    """A config as JSON-able values (paths and other objects as strings) for wandb's run config."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


class WandbSink(RecordSink):
    """An offline wandb run in ``run_dir/wandb`` (``wandb sync`` uploads it); the run's config as its config."""

    def __init__(self, run_dir: Path, project: str, config: Any = None, pipeline=None, eval_images: int = 1):
        wandb = self.wandb = import_backend("wandb", "wandb", "--logging.wandb")
        self.run = wandb.init(project=project, name=Path(run_dir).name, dir=str(run_dir), mode="offline",
                              config=_plain(config) if config is not None else None, reinit="create_new")
        self.pipeline, self.eval_images = pipeline, eval_images
        self._step_time = _StepTime()

    def write(self, record: dict[str, Any]) -> None:
        values: dict[str, Any] = flatten_record(record)
        step_time = self._step_time(record)
        if step_time is not None:
            values["train/step_time_s"] = step_time
        if record.get("kind") == "eval" and self.pipeline is not None and self.eval_images > 0:
            for i, image in enumerate(eval_view_images(self.pipeline.model, self.pipeline.datamanager.eval_dataset,
                                                       self.eval_images)):
                values[f"eval/view_{i}"] = self.wandb.Image(image.permute(1, 2, 0).numpy())
        if values:
            self.run.log(values, step=int(record.get("step", 0)))

    def close(self) -> None:
        self.run.finish()


def check_backends(logging: LoggingConfig) -> None:
    """The packages the asked-for backends need import (a :class:`UserError` with the install line when not):
    checked before the scene loads."""
    for enabled, module, flag in ((logging.tensorboard, "torch.utils.tensorboard", "--logging.tensorboard"),
                                  (logging.wandb, "wandb", "--logging.wandb")):
        if enabled:
            import_backend(module, flag.split(".")[-1], flag)


def logging_sinks(logging: LoggingConfig, run_dir: Path, pipeline=None, config: Any = None) -> list[RecordSink]:
    """The sinks ``logging`` asks for, writing into ``run_dir`` (tensorboard's event files directly in it, as
    nerfstudio writes them; wandb's in ``run_dir/wandb``)."""
    sinks: list[RecordSink] = []
    if logging.tensorboard:
        sinks.append(TensorboardSink(run_dir, pipeline, logging.eval_images))
    if logging.wandb:
        sinks.append(WandbSink(run_dir, logging.wandb_project, config, pipeline, logging.eval_images))
    return sinks
