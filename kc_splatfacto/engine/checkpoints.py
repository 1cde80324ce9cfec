"""Checkpoints ``nerfstudio_models/step-XXXXXXXXX.ckpt``: written atomically (temp file + ``os.replace``), so a crash
or Ctrl-C mid-write never leaves a truncated checkpoint under the final name."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import torch

from kc_splatfacto.atomic import atomic_write

CHECKPOINT_DIR = "nerfstudio_models"
CHECKPOINT_PATTERN = re.compile(r"^step-(\d{9})\.ckpt$")


def checkpoint_name(step: int) -> str:
    return f"step-{step:09d}.ckpt"


def save_checkpoint(directory: Path, step: int, payload: dict[str, Any], only_latest: bool = False) -> Path:
    """Write ``payload`` to ``directory/step-XXXXXXXXX.ckpt`` atomically; ``only_latest`` removes older ones after."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / checkpoint_name(step)
    atomic_write(path, lambda tmp: torch.save(payload, tmp))
    if only_latest:
        for other in list_checkpoints(directory):
            if other != path:
                other.unlink(missing_ok=True)
    return path


def list_checkpoints(directory: Path) -> list[Path]:
    """Checkpoints in ``directory``, oldest step first."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    found = [p for p in directory.iterdir() if CHECKPOINT_PATTERN.match(p.name)]
    return sorted(found, key=lambda p: int(CHECKPOINT_PATTERN.match(p.name).group(1)))


def find_checkpoint(load_dir: Path, step: int | None = None) -> Path:
    """The checkpoint of ``step`` (newest when None) in ``load_dir`` (a nerfstudio_models folder or a run folder)."""
    load_dir = Path(load_dir)
    if (load_dir / CHECKPOINT_DIR).is_dir():
        load_dir = load_dir / CHECKPOINT_DIR
    if not load_dir.is_dir():
        raise FileNotFoundError(f"checkpoint folder {load_dir} does not exist: pass a run's nerfstudio_models folder")
    checkpoints = list_checkpoints(load_dir)
    if not checkpoints:
        raise FileNotFoundError(f"no step-XXXXXXXXX.ckpt in {load_dir}")
    if step is None:
        return checkpoints[-1]
    path = load_dir / checkpoint_name(step)
    if not path.is_file():
        steps = [int(CHECKPOINT_PATTERN.match(p.name).group(1)) for p in checkpoints]
        raise FileNotFoundError(f"no checkpoint for step {step} in {load_dir} (has steps {steps})")
    return path


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    return torch.load(Path(path), map_location=map_location, weights_only=False)
