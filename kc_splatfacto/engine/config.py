"""Trainer, machine, pipeline and data-manager configs (nerfstudio names), saved to and loaded from ``config.yml``.

Every config is a dataclass; ``setup()`` builds what it configures. The YAML is PyYAML's full object dump (what
nerfstudio writes too): enough to rebuild the run exactly, including the dataparser config and the model config.
"""

from __future__ import annotations

import dataclasses
import datetime
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import tyro
import yaml

from kc_splatfacto.engine.optimizers import OptimizersConfig
from kc_splatfacto.model.splatfacto import SplatfactoModelConfig
from kc_splatfacto.atomic import atomic_write_text

TIMESTAMP_FORMAT = "%Y-%m-%d_%H%M%S"


def _gsplat_importable() -> bool:
    try:
        import gsplat  # noqa: F401
    except Exception:  # ImportError, or a CUDA build failing at import
        return False
    return True


@dataclass
class MachineConfig:
    """Where and how reproducibly to run."""

    seed: int = 42
    """seed of torch, numpy and python's random"""
    device: str = "auto"
    """'auto' (CUDA when available and gsplat imports, else CPU), 'cpu', 'cuda', 'cuda:1', ..."""

    def resolve_device(self) -> torch.device:
        if self.device == "auto":
            # CUDA only pays with gsplat's kernels: the rasterization backend "auto" refuses CUDA tensors without
            # gsplat (the compiled rasterizer is CPU-only), so without gsplat training stays on the CPU
            return torch.device("cuda" if torch.cuda.is_available() and _gsplat_importable() else "cpu")
        device = torch.device(self.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise RuntimeError(f"--machine.device {self.device}: CUDA is not available here; use 'cpu' or 'auto'")
        return device

    def seed_everything(self) -> None:
        random.seed(self.seed)
        np.random.seed(self.seed)
        torch.manual_seed(self.seed)


@dataclass
class DataManagerConfig:
    """Which scene to load and how; builds the train/test :class:`ImageDataset`s (see ``engine.datamanager``)."""

    data: Path | None = None
    """scene folder, or 'demo' for the generated demo scene"""
    dataparser: tyro.conf.Suppress[Any] = None
    """a dataparser config (detected from ``data`` when None)"""
    dataparser_name: str | None = None
    """force a registered dataparser by name instead of detecting the format"""
    downscale_factor: int | None = None
    """image downscale factor handed to the dataparser (None keeps the dataparser's own)"""
    eval_split: str = "test"
    """split evaluated during and after training"""

    def resolve_dataparser(self) -> Any:
        """The dataparser config to use: the explicit one, else detected from ``data``; downscale applied."""
        parser_config = self.dataparser
        if parser_config is None:
            if self.data is None:
                raise ValueError("no scene given: pass --data PATH (a scene folder, or 'demo' for the demo scene)")
            from kc_splatfacto.data import resolve_dataparser

            parser_config = resolve_dataparser(self.data, self.dataparser_name)
        if self.downscale_factor is not None and dataclasses.is_dataclass(parser_config):
            parser_config = dataclasses.replace(parser_config, downscale_factor=self.downscale_factor)
        return parser_config

    def setup(self, seed: int = 42) -> "DataManager":
        from kc_splatfacto.engine.datamanager import DataManager

        return DataManager(self, seed=seed)


@dataclass
class PipelineConfig:
    """The data manager and the model."""

    datamanager: DataManagerConfig = field(default_factory=DataManagerConfig)
    model: SplatfactoModelConfig = field(default_factory=SplatfactoModelConfig)


@dataclass
class LoggingConfig:
    """What the trainer writes while it runs."""

    steps_per_log: int = 10
    """train records in metrics.jsonl (with per-band kurtosis) every this many steps"""
    progress_bar: bool = True
    """one-line progress bar on stderr (it/s, ETA, loss, Gaussian count)"""
    profile_phases: bool = False
    """synchronize and time each phase of a step (render, losses, backward, optimizer, density control)"""
    steps_per_gradient_shares: int = 100
    """every this many steps a ``gradient_shares`` record: each loss term's image-gradient norm relative to the
    photometric term's (engine/gradient_shares.py; ~60 ms on a 192x128 CPU render, excluded from train_s); 0 turns it off"""


@dataclass
class TrainerConfig:
    """One training run (nerfstudio's ``TrainerConfig``/``ExperimentConfig`` field names)."""

    method_name: str = "splatfacto"
    experiment_name: str | None = None
    """run folder component; defaults to the scene folder's name"""
    output_dir: Path = Path("outputs")
    timestamp: str = "{timestamp}"
    """run folder component; '{timestamp}' is replaced by the start time"""
    data: Path | None = None
    """alias for --pipeline.datamanager.data"""
    max_num_iterations: int = 30000
    steps_per_save: int = 2000
    steps_per_eval_all_images: int = 1000
    """evaluate the whole eval split every this many steps (0 turns it off; the last step is always evaluated)"""
    eval_at_steps: tuple[int, ...] = ()
    """extra evaluation steps (e.g. log-spaced ones for quality-against-time reports)"""
    save_only_latest_checkpoint: bool = True
    load_dir: Path | None = None
    """resume from the newest checkpoint in this nerfstudio_models folder (or a run folder)"""
    load_step: int | None = None
    """resume from this step's checkpoint instead of the newest"""
    resume_from_other_run: bool = False
    """allow --load-dir of another scene's, method's or dataparser's run (continued in a new run folder)"""
    max_consecutive_bad_steps: int = 5
    """stop with an error after this many non-finite steps in a row (the last good state is saved)"""
    machine: MachineConfig = field(default_factory=MachineConfig)
    pipeline: PipelineConfig = field(default_factory=PipelineConfig)
    optimizers: OptimizersConfig = field(default_factory=OptimizersConfig)
    logging: LoggingConfig = field(default_factory=LoggingConfig)

    def resolve_aliases(self) -> None:
        """Fold ``--data`` into the data manager config."""
        if self.data is not None:
            self.pipeline.datamanager.data = self.data
            self.data = None

    def base_dir(self) -> Path:
        """``output_dir/experiment/method/timestamp``, with '{timestamp}' filled in."""
        experiment = self.experiment_name
        if experiment is None:
            data = self.pipeline.datamanager.data
            if data is None:  # a dataparser config given directly (kc-bench, tests): its scene folder
                data = getattr(self.pipeline.datamanager.dataparser, "data", None)
            experiment = Path(str(data)).name if data is not None else "unnamed"
        timestamp = self.timestamp
        if timestamp == "{timestamp}":
            timestamp = datetime.datetime.now().strftime(TIMESTAMP_FORMAT)
            self.timestamp = timestamp
        return Path(self.output_dir) / experiment / self.method_name / timestamp

    def save_config(self, path: Path) -> None:
        save_config(self, path)

    def setup(self) -> "Trainer":
        from kc_splatfacto.engine.trainer import Trainer

        return Trainer(self)


def save_config(config: TrainerConfig, path: Path) -> None:
    """Write the full config as YAML, atomically (temp file + rename)."""
    atomic_write_text(path, yaml.dump(config, Dumper=yaml.Dumper, sort_keys=False))


def load_config(path: Path | str) -> TrainerConfig:
    """Read a ``config.yml`` written by :func:`save_config`."""
    from kc_splatfacto.engine.config_file import read_config_file  # safe loader: only the project's configs

    return read_config_file(path)
