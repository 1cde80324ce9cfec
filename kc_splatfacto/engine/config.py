"""A run's ``config.yml`` as a :class:`~kc_splatfacto.engine.trainer.TrainerConfig`: :func:`load_config` and
:func:`save_config`, and the class names ``config.yml`` files of earlier versions give.

This module sits above the trainer (it imports ``TrainerConfig`` to say what a ``config.yml`` must hold); the reader
itself (:mod:`kc_splatfacto.engine.config_file`) sits below it, told the expected class by its caller. PyYAML wrote
``!!python/object:kc_splatfacto.engine.config.TrainerConfig`` (and ``...PipelineConfig``, ``...DataManagerConfig``,
``...MachineConfig``, ``...LoggingConfig``, ``...ViewerConfig``) before those classes moved beside what they build or
into :mod:`~kc_splatfacto.engine.base_config`; the reader resolves such a name by attribute lookup in this module,
which is why it imports them.
"""

from __future__ import annotations

from pathlib import Path

from kc_splatfacto.engine.base_config import LoggingConfig, MachineConfig, ViewerConfig
from kc_splatfacto.engine.config_file import read_config_file, save_config
from kc_splatfacto.engine.datamanager import DataManagerConfig
from kc_splatfacto.engine.pipeline import PipelineConfig
from kc_splatfacto.engine.trainer import TrainerConfig


def load_config(path: Path | str) -> TrainerConfig:
    """Read a ``config.yml`` written by :func:`save_config`: the run's ``TrainerConfig``, through a safe loader that
    rebuilds only the project's (and registered plugins') config dataclasses (a config file must not run code)."""
    return read_config_file(path, TrainerConfig)


__all__ = [
    "DataManagerConfig",
    "LoggingConfig",
    "MachineConfig",
    "PipelineConfig",
    "TrainerConfig",
    "ViewerConfig",
    "load_config",
    "save_config",
]
