"""Checks that run before a training run loads any data, and the resume rules.

:func:`plan_run` refuses settings that would silently do nothing or the wrong thing, before the (slow) scene load:
- an output folder that cannot be written (a resume of the same run writes in its own folder, checked instead;
  every field's type and range were checked when the trainer was built: :mod:`kc_splatfacto.engine.validation`);
- a resume (``load_dir``) whose checkpoint is past ``max_num_iterations`` (it would train nothing);
- a resume of another scene's, method's or dataparser's run: it would overwrite that run's ``config.yml`` and
  ``dataparser_transforms.json`` and delete its checkpoints. ``resume_from_other_run`` allows it, into a *new* run
  folder; the other run's files are never touched;
- a resume of the same run with other settings (:func:`setting_differences`, e.g. another downscale factor or SH
  degree): config.yml would describe the steps already taken wrongly. ``resume_from_other_run`` continues from the
  checkpoint with the new settings in a new run folder;
- a checkpoint that does not fit the config (another method or SH degree: ``checkpoints.check_checkpoint_fits``).

A run whose recorded scene no longer exists (the folder moved or was deleted) is the same run on the scene the command
names instead (``--data NEW_PATH``), provided that scene's cameras give the dataparser transform the run recorded in
its ``dataparser_transforms.json`` (:func:`check_moved_scene`); ``config.yml`` then records the new path.

:func:`plan_run` also resolves the run's dataparser, once (``auto`` detected from the scene, the scene path handed to
it): :attr:`RunPlan.dataparser` is what the data manager loads, what the resume checks compare and what ``config.yml``
records (:func:`recorded_dataparser`), so the scene path has one holder from then on: that config's ``data``.

A resume of the same run also removes checkpoint temp files a hard kill left behind and drops ``metrics.jsonl``
records written after the checkpoint (they will be written again), so the log has no duplicate or backwards steps.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.data.base import DataParserConfig, read_dataparser_transforms
from kc_splatfacto.data.demo import DemoDataParserConfig
from kc_splatfacto.data.detect import DEMO_NAME, AutoDataParserConfig
from kc_splatfacto.engine.checkpoints import (
    CHECKPOINT_DIR,
    IDENTITY_FIELDS,
    RUN_IDENTITY_KEY,
    check_checkpoint_fits,
    find_checkpoint,
    load_checkpoint,
    remove_orphan_temp_files,
)
from kc_splatfacto.engine.config_file import check_lines_kept, check_method_name, read_config_file
from kc_splatfacto.engine.datamanager import DataManager
from kc_splatfacto.errors import ResumeError, UserError
from kc_splatfacto.metrics import SSIM_WINDOW
from kc_splatfacto.plan.scene_plan import leaves

if TYPE_CHECKING:  # annotations only: the trainer imports this module
    from kc_splatfacto.engine.trainer import TrainerConfig
    from kc_splatfacto.model.splatfacto import SplatfactoModelConfig

OVERRIDE_FLAG = "--resume-from-other-run True"


@dataclass
class RunPlan:
    """Where a run writes and what it resumes from.

    Attributes:
        dataparser: the run's resolved dataparser config (the scene it trains on, and how it is read).
        run_dir: the folder to continue (a resume of the same run), or None for a new run folder.
        checkpoint: the loaded checkpoint payload to restore, or None.
        checkpoint_path: its file, or None.
        trimmed_records: metrics.jsonl records dropped because they were written after the checkpoint.
    """

    dataparser: DataParserConfig
    run_dir: Path | None = None
    checkpoint: dict[str, Any] | None = None
    checkpoint_path: Path | None = None
    trimmed_records: int = 0


def check_output_dir(config: TrainerConfig) -> None:
    """The folder new run folders go into must be writable; the message names ``--output-dir`` as the user gave it,
    or, when it is the default, says so (a user who never typed the flag is told what it is and that it exists)."""
    folder = Path(config.output_dir)
    default = next((f.default for f in dataclasses.fields(config) if f.name == "output_dir"), None)
    if isinstance(default, (str, os.PathLike)) and folder == Path(default):
        check_writable_folder(folder, "--output-dir's default",
                              "pass --output-dir with a folder you can write to, or run from another folder")
    else:
        check_writable_folder(folder, "--output-dir")


def check_writable_folder(folder: Path, what: str, fix: str | None = None) -> None:
    """Create ``folder`` if needed and write a probe file in it; a :class:`UserError` naming it (``what``: the flag
    that set it, or a description with ``fix`` saying what to do) when that fails."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        reason = "it is a file" if folder.is_file() else exc.strerror or exc
        raise UserError(
            f"{what} {folder} is not a writable folder ({reason}): {fix or f'choose another with {what}'}"
        ) from exc


def check_metrics_log(path: Path) -> None:
    """A resumed run appends to its ``metrics.jsonl``: one that cannot be opened for appending (read-only, a folder
    in its place) is a :class:`ResumeError` before the scene loads, not a traceback after it. A missing log is
    fine (the run folder is writable: the writer creates it)."""
    if not os.path.lexists(path):
        return
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_APPEND))
    except OSError as exc:
        fix = "move that folder away" if os.path.isdir(path) else f"make the file writable (chmod u+w {path})"
        raise ResumeError(
            f"the run's log {path} cannot be appended to ({exc.strerror or exc}), and a resume writes its records "
            f"there: {fix}, or resume from a copy of the run folder"
        ) from exc


def comparable_dataparser(config: TrainerConfig) -> DataParserConfig:
    """The dataparser config ``config`` trains with, for comparing two runs: resolved (``auto`` detected), or as given
    when its scene cannot be read (setup says what is wrong with the scene)."""
    datamanager = config.pipeline.datamanager
    try:
        return datamanager.resolve_dataparser()
    except (ValueError, OSError):
        return datamanager.dataparser


def scene_of(parser: DataParserConfig | None) -> str | None:
    """The scene a dataparser config reads, as an absolute path string ("demo" for the generated scene)."""
    if parser is None:
        return None
    if str(parser.data) == DEMO_NAME and isinstance(parser, (DemoDataParserConfig, AutoDataParserConfig)):
        return DEMO_NAME
    return str(Path(parser.data).expanduser().resolve())  # resolved: a scene reached through a symlink is the same


def moved_scene(stored_parser: DataParserConfig, current_parser: DataParserConfig) -> Path | None:
    """The scene ``stored_parser`` reads, when it no longer exists (moved or deleted) and ``current_parser``, of the
    same dataparser, names another scene that does; else None (the generated demo scene never moves)."""
    stored_scene, current_scene = scene_of(stored_parser), scene_of(current_parser)
    if DEMO_NAME in (stored_scene, current_scene) or stored_scene == current_scene:
        return None
    if type(stored_parser) is not type(current_parser) or Path(stored_parser.data).expanduser().exists():
        return None
    return Path(stored_parser.data) if Path(current_parser.data).expanduser().exists() else None


def check_moved_scene(dataparser: DataParserConfig, run_dir: Path, recorded_scene: Path | None) -> None:
    """A resume on the scene ``dataparser`` reads in place of the run's vanished ``recorded_scene`` (None: the scene
    did not move) must be on the same scene: its cameras give the dataparser transform (rotation, centre, scale) the
    run recorded in its ``dataparser_transforms.json``. A :class:`ResumeError` naming both scenes when they do not,
    before the resume writes anything (the scene's cameras are read here, once more than when it loads)."""
    recorded_path = run_dir / "dataparser_transforms.json"
    if recorded_scene is None or not recorded_path.is_file():  # nothing moved, or nothing recorded to compare with
        return
    recorded = read_dataparser_transforms(recorded_path)
    outputs = dataparser.setup().get_dataparser_outputs(split="train")
    transform = np.asarray(torch.as_tensor(outputs.dataparser_transform, dtype=torch.float64).cpu().numpy())[:3, :4]
    if np.allclose(transform, recorded.transform, rtol=1e-9, atol=1e-9) and math.isclose(
            float(outputs.dataparser_scale), recorded.scale, rel_tol=1e-9):
        return
    raise ResumeError(
        f"--data {dataparser.data} is not the scene of the run in {run_dir}: its cameras give another dataparser "
        f"transform than the run's {recorded_path} (the run trained on {recorded_scene}, which no longer exists). "
        f"Pass --data with the run's scene where it is now, or {OVERRIDE_FLAG} to continue from its checkpoint on "
        "this scene in a new run folder"
    )


def differences(stored: TrainerConfig, current: TrainerConfig, parser_settings: bool = False,
                stored_parser: DataParserConfig | None = None,
                current_parser: DataParserConfig | None = None) -> list[str]:
    """What makes ``current`` another run than ``stored``: method, scene, dataparser; with ``parser_settings`` also
    the dataparser's settings (e.g. its downscale factor; the scene path is compared as the scene). The two
    dataparser configs are :func:`comparable_dataparser` of each config unless the caller has them already."""
    found = []
    if stored.method_name != current.method_name:
        found.append(f"method {stored.method_name} vs {current.method_name}")
    stored_parser = stored_parser if stored_parser is not None else comparable_dataparser(stored)
    current_parser = current_parser if current_parser is not None else comparable_dataparser(current)
    stored_scene, current_scene = scene_of(stored_parser), scene_of(current_parser)
    if current_scene is not None and stored_scene != current_scene:
        found.append(f"scene {stored_scene} vs {current_scene}")
    if type(stored_parser) is not type(current_parser):
        found.append(f"dataparser {type(stored_parser).__name__} vs {type(current_parser).__name__}")
    elif parser_settings and dataclasses.is_dataclass(stored_parser) and dataclasses.is_dataclass(current_parser):
        stored_fields, current_fields = dataclasses.asdict(stored_parser), dataclasses.asdict(current_parser)
        changed = [f"{k} {stored_fields[k]} vs {v}" for k, v in current_fields.items()
                   if k != "data" and stored_fields.get(k) != v]
        if changed:
            found.append(f"dataparser settings ({', '.join(changed)})")
    return found


#: fields a resume may change: how long, how often and where it logs, evaluates and saves, on which device; every
#: other field (model, optimizers, dataparser settings, seed) must equal the stored run's, or config.yml would lie
#: about the steps already taken
RESUMABLE_FIELDS = (
    "method_name", "experiment_name", "output_dir", "timestamp", "max_num_iterations", "steps_per_save",
    "steps_per_eval_all_images", "eval_at_steps", "final_lpips_nets", "eval_lpips_nets", "save_only_latest_checkpoint", "load_dir",
    "load_step", "resume_from_other_run", "max_consecutive_bad_steps", "machine.device", "machine.memory_budget_gb",
    "machine.step_verdict",
    "logging",
    "pipeline.datamanager.dataparser", "pipeline.datamanager.eval_split",
    "pipeline.model.rasterizer",
)
#: dataparser fields that say where, not what: compared as the scene (data) or not at all (cache_dir)
PARSER_LOCATION_FIELDS = ("data", "cache_dir", "demo_cache_dir")


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def setting_differences(stored: TrainerConfig, current: TrainerConfig,
                        stored_parser: DataParserConfig | None = None,
                        current_parser: DataParserConfig | None = None) -> list[str]:
    """The settings (dotted names, stored vs current) in which ``current`` would train differently from ``stored``:
    every field but :data:`RESUMABLE_FIELDS`, and the resolved dataparser's settings (its scene is compared by
    :func:`differences`; the dataparser configs as there)."""
    found = []
    stored_leaves, current_leaves = leaves(stored), leaves(current)
    for name in sorted(set(stored_leaves) | set(current_leaves)):
        if any(name == f or name.startswith(f + ".") for f in RESUMABLE_FIELDS):
            continue
        a, b = stored_leaves.get(name, "(absent)"), current_leaves.get(name, "(absent)")
        if not _same(a, b):
            found.append(f"{name} {a!r} vs {b!r}")
    stored_parser = stored_parser if stored_parser is not None else comparable_dataparser(stored)
    current_parser = current_parser if current_parser is not None else comparable_dataparser(current)
    if type(stored_parser) is type(current_parser) and dataclasses.is_dataclass(stored_parser):
        a_fields, b_fields = leaves(stored_parser), leaves(current_parser)
        for name in sorted(set(a_fields) | set(b_fields)):
            if name in PARSER_LOCATION_FIELDS:
                continue
            a, b = a_fields.get(name, "(absent)"), b_fields.get(name, "(absent)")
            if not _same(a, b):
                found.append(f"pipeline.datamanager.dataparser.{name} {a!r} vs {b!r}")
    return found


def trim_metrics(path: Path, step: int) -> int:
    """Drop the records of ``metrics.jsonl`` with a step after ``step`` (and a torn last line); returns how many.

    Rewritten atomically, and only when something is dropped.
    """
    path = Path(path)
    if not path.is_file():
        return 0
    kept, dropped = [], 0
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.strip():
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError:  # a line cut by a hard kill
            dropped += 1
            continue
        if isinstance(record, dict) and isinstance(record.get("step"), int) and record["step"] > step:
            dropped += 1
            continue
        kept.append(line)
    if dropped:
        atomic_write_text(path, "".join(line + "\n" for line in kept))
    return dropped


def plan_run(config: TrainerConfig, map_location: Any = "cpu") -> RunPlan:
    """The checks of this module; returns the run's resolved dataparser, where the run writes and the checkpoint it
    resumes from. A scene that cannot be read (none given, unknown format) is refused here, before any checkpoint
    loads."""
    if config.load_dir is None or config.resume_from_other_run:  # a same-run resume writes into its own folder
        check_output_dir(config)
    dataparser = config.pipeline.datamanager.resolve_dataparser()
    if config.load_dir is None:
        return RunPlan(dataparser=dataparser)
    path = find_checkpoint(config.load_dir, config.load_step)
    checkpoint = load_checkpoint(path, map_location=map_location)
    step = int(checkpoint["step"])
    if step > config.max_num_iterations:
        raise ResumeError(
            f"checkpoint {path} is at step {step}, past --max-num-iterations {config.max_num_iterations}: resuming "
            f"would train nothing. Pass a larger --max-num-iterations to train on (kc-eval / kc-render read the run "
            "as it is)"
        )
    run_dir = path.parent.parent
    stored_path = run_dir / "config.yml"
    moved_from: Path | None = None
    if path.parent.name != CHECKPOINT_DIR or not stored_path.is_file():
        problems = [f"{path.parent} is not the nerfstudio_models folder of a run with a config.yml"]
    else:
        stored = read_config_file(stored_path, type(config))
        stored_parser = comparable_dataparser(stored)
        moved_from = moved_scene(stored_parser, dataparser)
        if moved_from is not None:  # the scene named here stands for the run's vanished one (its cameras: below)
            stored_parser = dataclasses.replace(stored_parser, data=dataparser.data)
        problems = differences(stored, config, stored_parser=stored_parser, current_parser=dataparser)
        if problems and not config.resume_from_other_run:
            if stored.method_name != config.method_name:  # a misspelt method_name, not another run's folder
                check_method_name(stored_path, stored.method_name,
                                  (checkpoint.get(RUN_IDENTITY_KEY) or {}).get("method_name"))
            check_lines_kept(stored_path, stored, _fields_behind(problems, checkpoint),
                             f"it differs from this command ({'; '.join(problems)})")
        if not problems:
            changed = setting_differences(stored, config, stored_parser, dataparser)
            if changed and config.resume_from_other_run:
                check_checkpoint_fits(checkpoint, config, path, same_method=False)
                return RunPlan(dataparser=dataparser, checkpoint=checkpoint, checkpoint_path=path)
            if changed:
                check_lines_kept(stored_path, stored, _fields_behind(changed, checkpoint),
                                 f"it differs from this command ({'; '.join(changed)})")
                raise ResumeError(
                    f"--load-dir {config.load_dir}: this command would train that run on with other settings than "
                    f"its {stored_path} ({'; '.join(changed)}), and config.yml would then describe its first "
                    f"{step} steps wrongly. Resume with the run's settings, or pass {OVERRIDE_FLAG} to continue "
                    "from its checkpoint with these settings in a new run folder"
                )
    if problems:
        if not config.resume_from_other_run:
            raise ResumeError(
                f"--load-dir {config.load_dir} is another run ({'; '.join(problems)}): resuming there would "
                f"overwrite its files. Pass {OVERRIDE_FLAG} to start a new run folder from that checkpoint "
                "(the other run is left untouched)"
            )
        check_checkpoint_fits(checkpoint, config, path, same_method=False)
        return RunPlan(dataparser=dataparser, checkpoint=checkpoint, checkpoint_path=path)
    check_checkpoint_fits(checkpoint, config, path)  # the run's config.yml and its checkpoint must agree
    check_moved_scene(dataparser, run_dir, moved_from)
    if config.resume_from_other_run and not os.access(run_dir, os.W_OK | os.X_OK):
        # a run folder this user cannot write (another user's): continued from its checkpoint in a new run folder
        return RunPlan(dataparser=dataparser, checkpoint=checkpoint, checkpoint_path=path)
    check_writable_folder(run_dir, "the run folder",
                          f"a resume writes there; copy it to a folder you own (cp -r {run_dir} COPY) and pass "
                          "--load-dir COPY, or pass --resume-from-other-run True to continue from its checkpoint in a "
                          "new run folder under --output-dir")
    check_metrics_log(run_dir / "metrics.jsonl")
    remove_orphan_temp_files(run_dir / CHECKPOINT_DIR, announce=lambda line: print(line, flush=True))
    trimmed = trim_metrics(run_dir / "metrics.jsonl", step)
    return RunPlan(dataparser=dataparser, run_dir=run_dir, checkpoint=checkpoint, checkpoint_path=path,
                   trimmed_records=trimmed)


def _fields_behind(differing: list[str], checkpoint: dict[str, Any]) -> dict[str, Any]:
    """{dotted config field: its value in the run (the checkpoint's record), or None} behind the entries of
    :func:`differences` and :func:`setting_differences` ("method a vs b", "scene ...", "pipeline.model.x a vs b")."""
    recorded = checkpoint.get(RUN_IDENTITY_KEY) or {}
    named = {"method": "method_name", "scene": "pipeline.datamanager.dataparser.data"}
    fields = {named.get(entry.split(" ", 1)[0], entry.split(" ", 1)[0]): None for entry in differing}
    for key, name in IDENTITY_FIELDS.items():
        if name in fields:
            fields[name] = recorded.get(key)
    return fields


def check_training_image_sizes(datamanager: DataManager, model_config: SplatfactoModelConfig) -> None:
    """Every training image must stay large enough for SSIM's window at the coarsest training resolution
    (1/2^num_downscales of the parsed size): refused before the first step, naming both settings that shrink it."""
    need = SSIM_WINDOW // 2 + 1
    cameras = datamanager.train_dataset.cameras
    divisor = 2 ** int(model_config.num_downscales)
    sizes = list(zip(cameras.widths.tolist(), cameras.heights.tolist()))
    index = min(range(len(sizes)), key=lambda i: min(sizes[i]))
    width, height = sizes[index]
    if min(width // divisor, height // divisor) >= need:
        return
    factor = datamanager.dataparser_config.downscale_factor
    name = datamanager.train_dataset.image_filenames[index]
    raise UserError(
        f"training image {name} is {width}x{height} after the dataparser's downscale_factor {factor}, and "
        f"{width // divisor}x{height // divisor} at the first training resolution (1/{divisor}, "
        f"pipeline.model.num_downscales {model_config.num_downscales}): SSIM needs at least {need} pixels a side. "
        "Lower --downscale-factor or --pipeline.model.num-downscales"
    )


def recorded_dataparser(parser: DataParserConfig) -> DataParserConfig:
    """The run's dataparser config as ``config.yml`` records it: a copy with its scene and cache paths absolute (when
    they exist), so kc-eval / kc-render work from any folder."""
    absolute: dict[str, Any] = {}
    for name in ("data", "cache_dir"):
        value = getattr(parser, name, None)
        if isinstance(value, (str, os.PathLike)) and str(value) != DEMO_NAME and Path(value).exists():
            absolute[name] = Path(value).expanduser().absolute()
    return dataclasses.replace(parser, **absolute)


def announce_seed_points(datamanager: DataManager, model_config: SplatfactoModelConfig) -> str | None:
    """One line when the scene has no seed points and the model falls back to random Gaussians (else None)."""
    if model_config.random_init or datamanager.seed_points() is not None:
        return None
    scene = datamanager.dataparser_config.data
    line = (
        f"no seed points in scene {scene}: starting from {model_config.num_random:,} random Gaussians "
        f"(--pipeline.model.num-random sets the count)"
    )
    print(line, flush=True)
    return line


__all__ = [
    "RunPlan",
    "announce_seed_points",
    "check_metrics_log",
    "check_moved_scene",
    "check_output_dir",
    "check_training_image_sizes",
    "check_writable_folder",
    "comparable_dataparser",
    "differences",
    "moved_scene",
    "plan_run",
    "recorded_dataparser",
    "scene_of",
    "setting_differences",
    "trim_metrics",
]

