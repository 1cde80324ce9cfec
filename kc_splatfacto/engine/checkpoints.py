"""Checkpoints ``nerfstudio_models/step-XXXXXXXXX.ckpt``: written atomically (temp file + ``os.replace``), so a crash
or Ctrl-C mid-write never leaves a truncated checkpoint under the final name.

Loading uses ``torch.load(weights_only=True)``: tensors, numbers, strings, containers and numpy's RNG state arrays,
never arbitrary pickled objects, so a checkpoint someone sent cannot run code. A file that does not load (truncated,
not a checkpoint, a full disk while writing) is a :class:`~kc_splatfacto.errors.CheckpointError` naming it.
"""

from __future__ import annotations

import errno
import pickle
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

from kc_splatfacto.atomic import atomic_write
from kc_splatfacto.errors import CheckpointError

CHECKPOINT_DIR = "nerfstudio_models"
CHECKPOINT_PATTERN = re.compile(r"^step-(\d{9})\.ckpt$")
#: temp files of :func:`kc_splatfacto.atomic.atomic_write` for checkpoints (left behind only by a hard kill)
TEMP_PATTERN = re.compile(r"^\.step-\d{9}\.ckpt\..*\.tmp$")


class CheckpointNotFoundError(CheckpointError, FileNotFoundError):
    """No checkpoint where one was asked for."""


class CheckpointMismatchError(CheckpointError):
    """A checkpoint whose run identity differs from the config's; ``recorded`` holds each differing config field
    (dotted name) with the checkpoint's value, so a caller holding the config file can say whether the file lost
    that line."""

    def __init__(self, message: str, recorded: dict[str, Any]):
        super().__init__(message)
        self.recorded = recorded


def checkpoint_step(path: Path) -> int:
    """The step of a checkpoint file named by :func:`checkpoint_name`."""
    match = CHECKPOINT_PATTERN.match(Path(path).name)
    if match is None:
        raise ValueError(f"{path} is not a checkpoint file name (step-NNNNNNNNN.ckpt)")
    return int(match.group(1))


def checkpoint_name(step: int) -> str:
    return f"step-{step:09d}.ckpt"


def save_checkpoint(directory: Path, step: int, payload: dict[str, Any], only_latest: bool = False) -> Path:
    """Write ``payload`` to ``directory/step-XXXXXXXXX.ckpt`` atomically; ``only_latest`` removes older ones after."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / checkpoint_name(step)
    try:
        atomic_write(path, lambda tmp: torch.save(payload, tmp))
    except (OSError, RuntimeError) as exc:  # torch.save reports a full disk as RuntimeError from its zip writer
        if isinstance(exc, OSError) and exc.errno not in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS):
            raise
        if isinstance(exc, RuntimeError) and not any(
            hint in str(exc).lower() for hint in ("write", "unexpected pos", "file", "space")
        ):  # PyTorch's zip writer reports a full disk as "unexpected pos N vs M" (its stream fell short)
            raise
        raise CheckpointError(
            f"could not write checkpoint {path} ({exc}): is the disk full? Free space and resume with --load-dir "
            f"{directory} (the previous checkpoint there is intact)"
        ) from exc
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
    return sorted(found, key=checkpoint_step)


def find_checkpoint(load_dir: Path, step: int | None = None) -> Path:
    """The checkpoint of ``step`` (newest when None) in ``load_dir`` (a nerfstudio_models folder, a run folder, or
    a checkpoint file itself)."""
    load_dir = Path(load_dir)
    if load_dir.is_file():
        match = CHECKPOINT_PATTERN.match(load_dir.name)
        if match is None:
            raise CheckpointNotFoundError(
                f"{load_dir} is a file but not a step-XXXXXXXXX.ckpt checkpoint: pass a run folder, its "
                "nerfstudio_models folder or one of its checkpoints"
            )
        if step is not None and int(match.group(1)) != step:
            raise CheckpointNotFoundError(
                f"{load_dir} is the checkpoint of step {int(match.group(1))}, not of the step {step} asked for: pass "
                "its folder to choose a step, or leave the step out"
            )
        return load_dir
    if (load_dir / CHECKPOINT_DIR).is_dir():
        load_dir = load_dir / CHECKPOINT_DIR
    if not load_dir.is_dir():
        raise CheckpointNotFoundError(
            f"checkpoint folder {load_dir} does not exist: pass a run folder, its nerfstudio_models folder or a "
            "step-XXXXXXXXX.ckpt file"
        )
    checkpoints = list_checkpoints(load_dir)
    if not checkpoints:
        raise CheckpointNotFoundError(
            f"no checkpoint (step-XXXXXXXXX.ckpt) in {load_dir}: the run stopped before its first one was written; "
            "train it again, or pass a run folder that has one"
        )
    if step is None:
        return checkpoints[-1]
    path = load_dir / checkpoint_name(step)
    if not path.is_file():
        steps = [checkpoint_step(p) for p in checkpoints]
        raise CheckpointNotFoundError(f"no checkpoint for step {step} in {load_dir} (has steps {steps})")
    return path


#: what a checkpoint records about the run that wrote it (beside the state), to refuse loading it into another
RUN_IDENTITY_KEY = "run"
#: the config field each identity entry comes from
IDENTITY_FIELDS = {"method_name": "method_name", "sh_degree": "pipeline.model.sh_degree"}


def run_identity(config: Any) -> dict[str, Any]:
    """The settings a checkpoint's tensors depend on: the method and the SH degree (features_rest's width)."""
    return {"method_name": str(config.method_name), "sh_degree": int(config.pipeline.model.sh_degree)}


def check_checkpoint_fits(checkpoint: dict[str, Any], config: Any, path: Path, same_method: bool = True) -> None:
    """A :class:`CheckpointError` when ``checkpoint`` was written by a run of another method (unless not
    ``same_method``) or SH degree than ``config`` describes (its recorded identity, and the SH coefficients its
    Gaussians hold)."""
    recorded = checkpoint.get(RUN_IDENTITY_KEY) or {}
    expected = run_identity(config)
    if not same_method:
        expected.pop("method_name")
    differing = {key: recorded[key] for key, value in expected.items() if key in recorded and recorded[key] != value}
    found = [f"{IDENTITY_FIELDS[key]} {recorded[key]!r} in the checkpoint vs {expected[key]!r} in the config"
             for key in differing]
    rest = checkpoint.get("model", {}).get("features_rest") if isinstance(checkpoint.get("model"), dict) else None
    if rest is not None and "sh_degree" not in recorded and getattr(rest, "ndim", 0) == 3:
        degree = expected["sh_degree"]
        if rest.shape[1] != (degree + 1) ** 2 - 1:
            found.append(f"features_rest holds {rest.shape[1]} SH coefficients per colour, pipeline.model.sh_degree {degree} has "
                         f"{(degree + 1) ** 2 - 1}")
            differing["sh_degree"] = round((rest.shape[1] + 1) ** 0.5) - 1
    if found:
        raise CheckpointMismatchError(
            f"checkpoint {path} was written by another run ({'; '.join(found)}): it does not fit this config; "
            "pass the config.yml of the run that wrote it",
            {IDENTITY_FIELDS[key]: value for key, value in differing.items()},
        )


def remove_orphan_temp_files(directory: Path, announce: Callable[[str], object] | None = None) -> list[Path]:
    """Remove checkpoint temp files a hard kill (kill -9, power loss) left mid-write in ``directory``; ``announce``
    (e.g. ``print``) gets one line naming them and their size when there were any."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    orphans = [p for p in directory.iterdir() if TEMP_PATTERN.match(p.name) and p.is_file()]
    size = 0
    for orphan in orphans:
        try:
            size += orphan.stat().st_size
        except OSError:
            pass
        orphan.unlink(missing_ok=True)
    if orphans and announce is not None:
        names = ", ".join(sorted(p.name for p in orphans))
        announce(f"removed {len(orphans)} unfinished checkpoint file{'s' if len(orphans) > 1 else ''} "
                 f"({size / 1e6:.1f} MB) that a killed run left in {directory}: {names}")
    return orphans


def _numpy_rng_globals() -> list:
    """What ``np.random.get_state()`` pickles to: numpy's array reconstruction, ndarray, dtype (data only)."""
    multiarray = getattr(np, "_core", None) or np.core
    return [multiarray.multiarray._reconstruct, np.ndarray, np.dtype, type(np.dtype(np.uint32))]


def as_random_state(state: Any) -> tuple:
    """Python's ``random`` state after a round trip through a checkpoint (lists where ``getstate`` gave tuples),
    ready for ``setstate``."""
    version, internal, gauss = state
    return (version, tuple(internal), gauss)


def load_checkpoint(path: Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """The payload of a checkpoint file, loaded with ``weights_only=True``; a :class:`CheckpointError` naming the
    file when it is missing, truncated, not a checkpoint, or holds objects other than data."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist: pass a run's nerfstudio_models folder")
    try:
        with torch.serialization.safe_globals(_numpy_rng_globals()):
            payload = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        # torch words a refused global three ways: "Unsupported global: GLOBAL X" (not allowlisted), "unsupported
        # GLOBAL X whose module M is blocked" (os, subprocess, ...), "but got <class 'X'>" (a numpy dtype)
        refused = re.search(r"[Uu]nsupported (?:global: )?GLOBAL (\S+)|but got <class '([^']+)'>", str(exc))
        if refused:  # weights_only refused a global: the file asks to run code, not to rebuild data
            raise CheckpointError(
                f"checkpoint {path} holds objects other than tensors and plain values "
                f"({refused.group(1) or refused.group(2)}); "
                "refusing to load it, since it could run code"
            ) from exc
        raise CheckpointError(
            f"checkpoint {path} is truncated or not a checkpoint ({str(exc)[:200]}): resume from an older step "
            "with --load-step, or delete it"
        ) from exc
    except Exception as exc:  # noqa: BLE001  garbage bytes fail in the unpickler in any way (IndexError, KeyError,
        # struct.error, EOFError, BadZipFile, ...): all of them mean the file is not a readable checkpoint
        raise CheckpointError(
            f"checkpoint {path} is truncated or not a checkpoint ({type(exc).__name__}: {str(exc)[:200]}): "
            "resume from an older step with --load-step, or delete it"
        ) from exc
    if not isinstance(payload, dict) or "model" not in payload or "step" not in payload:
        raise CheckpointError(f"checkpoint {path} is not a kc-splatfacto checkpoint (no 'model' and 'step')")
    return payload
