"""One run of a study: what it is (:class:`RunSpec`), and how it is trained, resumed or reused
(:func:`execute_run`), wherever it executes (in the study's process, or as a Ray task on another machine).

A run's folder is ``runs_dir/<scene>/<method>/seed<seed>``; the study decides from that folder alone what to do with
the run (``--resume``): reuse it when it holds the final evaluation, continue it from its last checkpoint when it was
interrupted, start it again when it has no checkpoint. A folder trained with other settings is never mixed in.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from kc_splatfacto.atomic import atomic_write_bytes, atomic_write_text
from kc_splatfacto.engine.checkpoints import CHECKPOINT_DIR, checkpoint_step, find_checkpoint, list_checkpoints
from kc_splatfacto.engine.config import load_config
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.run_guard import differences
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.errors import UserError
from kc_splatfacto.plan.scene_plan import PLAN_FILE, read_choices, reapply_choices
from kc_splatfacto.study.machine import MACHINE_FILE, read_machines, record_machine

RESULT_FILES = ("config.yml", "metrics.jsonl", "dataparser_transforms.json", MACHINE_FILE, PLAN_FILE)
"""a run's small files, sent back by a task for a study whose machines share no filesystem (never checkpoints)"""
TIMING_KEYS = frozenset({"elapsed_s", "train_s", "train_cpu_s", "render_fps", "path"})
"""record fields that measure the machine, not the training: they differ between two runs with equal numbers"""


class StudySettingsError(UserError, ValueError):
    """A run folder the study would reuse or continue holds a run of other settings."""


@dataclass
class RunSpec:
    """One (scene, method, seed) of a study, with the trainer config that trains it.

    ``run_dir`` is absolute (a task may run in another working directory); ``label`` is how reports name it.
    """

    index: int
    scene: str
    method: str
    seed: int
    run_dir: Path
    config: Any
    max_steps: int
    label_dir: str = ""

    @property
    def name(self) -> str:
        return f"{self.scene} {self.method} seed {self.seed}"


def check_same_settings(run_dir: Path, config: Any) -> None:
    """A run folder the study would reuse or continue must have been trained with the settings ``config`` asks for:
    model, seed, optimizers, scene and dataparser with its settings (e.g. the downscale factor), as its
    ``config.yml`` records them (with the scene plan's choices, where the run has a ``plan.json``). Anything else is a
    :class:`StudySettingsError` naming the folder and what differs, never a finished run of another setting silently
    reported as this one."""
    saved_path = Path(run_dir) / "config.yml"
    if not saved_path.is_file():
        return
    saved = load_config(saved_path)
    plan = Path(run_dir) / PLAN_FILE
    if plan.is_file() and config.pipeline.model.plan == "on":  # config.yml records the planned values
        config = copy.deepcopy(config)
        reapply_choices(config, read_choices(plan))
    mismatch = [
        name for name, a, b in (
            ("pipeline.model", dataclasses.asdict(saved.pipeline.model), dataclasses.asdict(config.pipeline.model)),
            ("machine.seed", saved.machine.seed, config.machine.seed),
            ("optimizers", dataclasses.asdict(saved.optimizers), dataclasses.asdict(config.optimizers)),
        ) if a != b
    ] + differences(saved, config, parser_settings=True)
    if mismatch:
        hint = ""
        if saved.pipeline.model.plan != config.pipeline.model.plan:  # e.g. a study of before the plan was on
            hint = (f" (the scene plan: {saved.pipeline.model.plan} in that run, {config.pipeline.model.plan} here; "
                    f"--set pipeline.model.plan={saved.pipeline.model.plan} asks for that run's)")
        raise StudySettingsError(
            f"--resume: {run_dir} was trained with another {', '.join(mismatch)} than this command asks for{hint}; "
            f"rerun with the original command, or pass another --runs-dir"
        )


def resume_point(run_dir: Path, config: Any) -> Path | None:
    """Prepare an interrupted run folder for ``--resume``: the checkpoint folder to continue from, or None (start
    again).

    The folder must hold a run of the same settings (:func:`check_same_settings`). Records logged after the
    checkpoint's step are cut from ``metrics.jsonl`` (atomically), since the resumed run logs them again; without a
    checkpoint the log is moved aside to ``metrics.interrupted.jsonl`` and the run starts from scratch.
    """
    check_same_settings(run_dir, config)
    log = run_dir / "metrics.jsonl"
    checkpoints = list_checkpoints(run_dir / CHECKPOINT_DIR)
    if not checkpoints:
        set_aside_first_attempt(run_dir)
        return None
    step = checkpoint_step(checkpoints[-1])
    if log.is_file():
        kept = []
        for line in log.read_text().splitlines():
            if not line.strip():
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError:  # a line cut by the interruption
                continue
            if int(record.get("step", 0)) <= step:
                kept.append(line)
        atomic_write_text(log, "".join(line + "\n" for line in kept))
    return checkpoints[-1].parent


def set_aside_first_attempt(run_dir: Path) -> None:
    """Move what a run cut before its first checkpoint left in ``run_dir`` out of the way of the new attempt: its
    log to ``metrics.interrupted.jsonl`` and its checkpoint folder (empty, or holding the temp file of the write the
    cut stopped) to ``nerfstudio_models.interrupted``. Left in place, either one makes the trainer start the new
    attempt in a sibling folder (``seed0_1``: a fresh run never writes over a log or a checkpoint folder), where the
    study would not find its ``machine.json``."""
    moves = (("metrics.jsonl", "metrics.interrupted.jsonl"), (CHECKPOINT_DIR, f"{CHECKPOINT_DIR}.interrupted"))
    for name, aside in moves:
        if (run_dir / name).exists():
            if (run_dir / aside).is_dir():  # an earlier attempt's, which held no checkpoint either
                shutil.rmtree(run_dir / aside)
            (run_dir / name).replace(run_dir / aside)


def final_step(run_dir: Path, max_steps: int) -> int:
    """The step a run of budget ``max_steps`` ends at: ``max_steps``, or the scene plan's end where the run's
    ``plan.json`` planned it for that budget (the plan stops earlier, never later; a plan made for another budget
    does not say where this one ends)."""
    path = Path(run_dir) / PLAN_FILE
    if not path.is_file():
        return max_steps
    asked, chosen = read_choices(path).get("max_num_iterations", (None, None))
    return int(chosen) if asked == max_steps and chosen is not None else max_steps


def is_finished(run_dir: Path, max_steps: int) -> bool:
    """Whether ``run_dir``'s log holds the evaluation of its final step (:func:`final_step`: the run is complete)."""
    log = Path(run_dir) / "metrics.jsonl"
    if not log.is_file():
        return False
    try:
        records = read_metrics(log)
    except ValueError:
        return False
    end = final_step(run_dir, max_steps)
    return any(r.get("kind") == "eval" and int(r.get("step", -1)) == end for r in records)


def execute_run(spec: RunSpec, *, resume: bool, send_files: bool = False) -> dict[str, Any]:
    """Train, continue or reuse one run; never raises for the run's own failure (the study goes on without it).

    Returns a result: ``index``, ``status`` (``trained``, ``resumed``, ``restarted``, ``reused``, ``interrupted`` or
    ``failed``), ``run_dir``, ``wall_s``, ``records`` (the run's ``metrics.jsonl``; empty when it failed),
    ``machines`` (its ``machine.json``: which CPU trained which stretch, :mod:`~kc_splatfacto.study.machine`), ``error``
    (``"Type: message"`` and the innermost frame, when failed) and, with ``send_files``, ``files``: the run's small
    files (:data:`RESULT_FILES`) as bytes, so a study on machines without a shared filesystem gets them back.
    A Ctrl-C (``KeyboardInterrupt``) is not a failure: it propagates.
    """
    start = time.perf_counter()
    result: dict[str, Any] = {"index": spec.index, "run_dir": str(spec.run_dir), "records": [], "machines": [],
                              "error": None}
    try:
        config = spec.config
        if resume and is_finished(spec.run_dir, spec.max_steps):
            check_same_settings(spec.run_dir, config)
            run_dir, status = spec.run_dir, "reused"
        else:
            status = "trained"
            if resume and spec.run_dir.is_dir():
                config = dataclasses.replace(config, load_dir=resume_point(spec.run_dir, config))
                status = "resumed" if config.load_dir is not None else "restarted"
            trainer = Trainer(config)
            from_step = checkpoint_step(find_checkpoint(config.load_dir)) if config.load_dir is not None else 0
            record_machine(spec.run_dir, from_step, threads=torch.get_num_threads())
            run_dir = Path(trainer.train())
            if run_dir.absolute() != spec.run_dir.absolute():  # its machine.json and the study's report are there
                raise RuntimeError(f"the run trained into {run_dir}, not the study's folder {spec.run_dir}")
            if trainer.interrupted:
                status = "interrupted"
        result["run_dir"] = str(run_dir)
        # a run reused by a study of a shorter budget (its first steps are that budget's run: the schedules do not
        # depend on it) reports up to the budget, never a later evaluation as its final one
        records = read_metrics(run_dir / "metrics.jsonl")
        result["records"] = [r for r in records if int(r.get("step", 0)) <= spec.max_steps]
        result["machines"] = read_machines(run_dir)
        if send_files:
            result["files"] = {n: (run_dir / n).read_bytes() for n in RESULT_FILES if (run_dir / n).is_file()}
    except Exception as exc:  # noqa: BLE001  (a run's failure is reported; the other runs go on)
        status = "failed"
        frame = traceback.extract_tb(exc.__traceback__)[-1] if exc.__traceback__ else None
        where = f" (at {Path(frame.filename).name}:{frame.lineno})" if frame else ""
        result["error"] = f"{type(exc).__name__}: {exc}{where}"
    result["status"] = status
    result["wall_s"] = time.perf_counter() - start
    return result


def write_returned_files(run_dir: Path, files: dict[str, bytes]) -> None:
    """Write the files a remote task sent back into ``run_dir`` (atomically), where they are missing or differ:
    with a shared filesystem they are already there and nothing is written."""
    run_dir.mkdir(parents=True, exist_ok=True)
    for name, content in files.items():
        path = run_dir / name
        if not path.is_file() or path.read_bytes() != content:
            atomic_write_bytes(path, content)


def numbers_only(records: list[dict]) -> list[dict]:
    """``records`` without the fields that measure the machine (:data:`TIMING_KEYS`): what two runs of the same
    numerics share exactly, wherever and however fast they ran."""
    return [{k: v for k, v in r.items() if k not in TIMING_KEYS} for r in records]
