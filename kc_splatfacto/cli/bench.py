"""``kc-bench``: quality against training time for several methods, scenes and seeds under one step budget.

Each (scene, method, seed) is one ordinary training run through :class:`Trainer`, evaluated on the test split at
log-spaced steps (``eval_at_steps``); the report (:mod:`kc_splatfacto.analysis.report`) then writes, under
``--output-dir``: ``evals.csv`` / ``evals.json`` (every evaluation), ``summary.json``, ``results.md`` (final metrics
with deltas vs the baseline, also per seed), ``<metric>_vs_time.png``, ``kurtosis_gap_<scene>.png`` (the render-vs-GT
band-kurtosis gap over training) and ``command.txt`` (the exact command line). The report is
rewritten after every finished run, so an interrupted benchmark still leaves the runs it finished.

``--resume`` continues a stopped study where it stopped, with the same command line plus ``--resume``: a run whose
folder already holds its final evaluation is reused as it is; an interrupted run (its folder holds a checkpoint,
written every ``--steps-per-save`` steps) continues from its last checkpoint in the same folder, its
``metrics.jsonl`` first cut back to that step so that nothing is logged twice; an interrupted run without a
checkpoint starts again (its old log kept as ``metrics.interrupted.jsonl``). A run folder, finished or not, whose
``config.yml`` holds another model config, seed, optimizer, scene or dataparser setting than the command asks for is
an error, not silently mixed in.

Runs execute one after another in this process (``--workers 1``, the default), or as Ray tasks
(:mod:`kc_splatfacto.study.runners`): ``--workers N`` starts an embedded local Ray cluster running N at once,
``--ray-address`` (or ``RAY_ADDRESS``) submits them to a running cluster; ``--threads`` sets each run's torch and
numba threads. The run folders, the report and the numbers are the same either way (``docs/study.md``). A failed run
is reported in ``runs.json`` and on stderr while the others go on (exit status 1); Ctrl-C or SIGTERM keeps every
finished run (exit status 130) and ``--resume`` continues. ``--report-only`` writes the report of the finished runs
and trains nothing.

Example (three paired seeds at 7000 steps of Splatfacto's schedule)::

    kc-bench --data ../shared/data/fern-12 --downscale-factor 2 --methods splatfacto kc-splatfacto \\
        --seeds 0 1 2 --max-num-iterations 7000 --num-evals 10 --time-key train_cpu_s \\
        --output-dir results/fern-12 --workers 2 --threads 1
"""

from __future__ import annotations

import argparse
import copy
import functools
import json
import os
import shlex
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kc_splatfacto.analysis.along_training import write_along_training
from kc_splatfacto.analysis.diagnostics import plot_kurtosis_gap_comparison
from kc_splatfacto.analysis.plans import write_plan_table
from kc_splatfacto.analysis.report import eval_rows, plot_gradient_shares, write_report
from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.cli.main import INTERRUPTED_EXIT, check_folder_can_hold, did_you_mean, path_flag, run_cli
from kc_splatfacto.cli.train import override_config
from kc_splatfacto.data.detect import AutoDataParserConfig
from kc_splatfacto.engine.base_config import MachineConfig
from kc_splatfacto.engine.checkpoints import (
    CHECKPOINT_DIR,
    checkpoint_step,
    list_checkpoints,
    remove_orphan_temp_files,
)
from kc_splatfacto.engine.memory import BUDGET_FRACTION, cpu_memory_it_may_use
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.optimizers import SPLATFACTO_SCHEDULE_STEPS  # ``--steps-scale auto``: budget / this
from kc_splatfacto.engine.validation import ConfigValueError, validate_config
from kc_splatfacto.errors import UserError
from kc_splatfacto.registry import discover_methods
from kc_splatfacto.study.machine import machine_kinds
from kc_splatfacto.study.runners import RayRunner, SerialRunner, StudyInterrupted
from kc_splatfacto.study.runs import RunSpec, check_same_settings, final_step, is_finished


class BenchArgumentError(UserError, ValueError):
    """A kc-bench argument that cannot work (a budget below 1, a bad --set, an unknown method)."""

DEFAULT_METHODS = ("splatfacto", "kc-splatfacto")
ARM_VARIANTS = {"plan": "on", "fixed": "off"}
"""``METHOD+plan`` and ``METHOD+fixed``: the registered method with the scene plan (``pipeline.model.plan``) on or off"""
DEFAULT_BASELINE = "splatfacto"
#: the report folder when --output-dir is not given
DEFAULT_OUTPUT_DIR = Path("bench")


def log_spaced_steps(max_steps: int, num: int) -> tuple[int, ...]:
    """About ``num`` distinct steps in [1, max_steps], geometrically spaced, always ending at ``max_steps``."""
    if max_steps < 1:
        raise BenchArgumentError(f"max_steps must be >= 1, got {max_steps}")
    if num < 1:
        raise BenchArgumentError(f"the number of evaluations must be >= 1, got {num}")
    steps = np.unique(np.round(np.geomspace(1, max_steps, num)).astype(int))
    return tuple(int(s) for s in sorted(set(steps.tolist()) | {max_steps}))


def evaluation_steps(max_steps: int, num: int, extra: Sequence[int] = ()) -> tuple[int, ...]:
    """:func:`log_spaced_steps` plus the ``extra`` steps (e.g. 7000 in a 30000-step run); each in [1, max_steps]."""
    outside = [s for s in extra if not 1 <= s <= max_steps]
    if outside:
        raise BenchArgumentError(f"--eval-at-steps {outside}: evaluation steps must lie in [1, --max-num-iterations={max_steps}]")
    return tuple(sorted(set(log_spaced_steps(max_steps, num)) | {int(s) for s in extra}))


def split_arm(arm: str) -> tuple[str, str | None]:
    """``'kc-splatfacto+plan'`` -> ``('kc-splatfacto', 'plan')``; a plain method name -> ``(name, None)``."""
    method, sep, variant = arm.rpartition("+")
    return (method, variant) if sep and method else (arm, None)


def check_arms(arms: Sequence[str], methods_available: dict) -> None:
    """Every ``--methods`` entry is a registered method, or one with a known ``+VARIANT`` (:data:`ARM_VARIANTS`)."""
    unknown = []
    for arm in arms:
        method, variant = split_arm(arm)
        if method not in methods_available or (variant is not None and variant not in ARM_VARIANTS):
            unknown.append(arm)
    if unknown:
        variants = ", ".join(f"METHOD+{v}" for v in ARM_VARIANTS)
        raise BenchArgumentError(f"unknown method(s) {unknown}; registered: {', '.join(methods_available) or 'none'} "
                                 f"(and {variants}: the scene plan on or off)")


def scene_downscale_factors(data: Sequence[str], factors: Sequence[int] | None) -> dict[str, int | None]:
    """``--downscale-factor``: one factor for every scene, or one per ``--data`` entry in the same order."""
    if not factors:
        return {str(d): None for d in data}
    if len(factors) == 1:
        return {str(d): factors[0] for d in data}
    if len(factors) != len(data):
        raise BenchArgumentError(
            f"--downscale-factor: give one factor or one per scene ({len(data)} scenes), got {len(factors)}"
        )
    return {str(d): f for d, f in zip(data, factors)}


def apply_override(config: Any, assignment: str) -> Any:
    """``config`` with one dotted field set from ``'pipeline.model.frequency.kc_weight=1e-4'``, parsed by kc-train's
    own parser (:func:`kc_splatfacto.cli.train.override_config`): the same flags, types, choices and errors as
    ``kc-train METHOD --pipeline.model.frequency.kc-weight 1e-4``. Several values (a tuple field) are separated by spaces."""
    key, sep, value = assignment.partition("=")
    if not sep or not key.strip():
        raise BenchArgumentError(f"--set '{assignment}': expected dotted.field=value")
    flag = "--" + key.strip().replace("_", "-")
    try:
        return override_config(config, [flag, *value.split()])
    except SystemExit as exc:  # tyro printed why (unknown field, wrong type, not a choice)
        raise BenchArgumentError(f"--set '{assignment}': not a valid override of the {config.method_name} config") from exc


def build_run_config(
    spec_config: Any,
    *,
    method: str,
    data: Path,
    seed: int,
    max_steps: int,
    eval_steps: Sequence[int],
    runs_dir: Path,
    experiment: str,
    downscale_factor: int | None,
    steps_scale: float | None,
    device: str,
    overrides: Sequence[str] = (),
) -> Any:
    """A fresh TrainerConfig for one bench run (the registered config is never modified)."""
    config = copy.deepcopy(spec_config)
    config.method_name = method
    config.experiment_name = experiment
    config.output_dir = runs_dir
    config.timestamp = f"seed{seed}"
    config.pipeline.datamanager.dataparser = AutoDataParserConfig(data=Path(data))  # detected from the scene
    if downscale_factor is not None:
        config.pipeline.datamanager.dataparser.downscale_factor = downscale_factor
    config.max_num_iterations = max_steps
    config.eval_at_steps = tuple(eval_steps)
    config.steps_per_eval_all_images = 0  # only the log-spaced steps (and the last one)
    config.steps_per_save = max_steps
    config.machine.seed = seed
    config.machine.device = device
    config.logging.progress_bar = False
    if steps_scale is not None:
        config.pipeline.model.steps_scale = steps_scale
    for assignment in overrides:
        config = apply_override(config, assignment)
    return config


def check_run_config(config: Any, method: str) -> None:
    """A value the study's flags put out of its range (``--set``, ``--max-num-iterations``, ...) refuses the study
    before any run starts, in one line, rather than failing every run of it (each trainer checks its config again)."""
    try:
        validate_config(config)
    except ConfigValueError as exc:
        raise BenchArgumentError(f"--set or the study's flags give the {method} runs a value out of range: {exc}") from exc


def plan_runs(args: argparse.Namespace, methods_available: dict, runs_dir: Path) -> list[RunSpec]:
    """Every run of the study, seed-major (seed, then scene, then method): a study stopped part-way has the same
    number of paired seeds on every scene. Each run's config is built (and its overrides checked) before any runs."""
    eval_steps = evaluation_steps(args.max_num_iterations, args.num_evals, args.eval_at_steps)
    if args.steps_scale == "auto":
        steps_scale = args.max_num_iterations / SPLATFACTO_SCHEDULE_STEPS
    elif args.steps_scale == "none":
        steps_scale = None
    else:
        steps_scale = float(args.steps_scale)
    downscale = scene_downscale_factors(args.data, args.downscale_factor)
    specs: list[RunSpec] = []
    for seed in args.seeds:
        for data in args.data:
            scene = scene_name(data)
            for arm in args.methods:
                method, variant = split_arm(arm)
                config = build_run_config(
                    methods_available[method].config, method=method,
                    data=Path(data) if str(data) == "demo" else Path(data).absolute(), seed=seed,
                    max_steps=args.max_num_iterations, eval_steps=eval_steps, runs_dir=runs_dir.absolute(),
                    experiment=scene, downscale_factor=downscale[str(data)], steps_scale=steps_scale,
                    device=args.device, overrides=args.set,
                )
                config.steps_per_save = args.steps_per_save if args.steps_per_save > 0 else args.max_num_iterations
                if variant is not None:  # the method's own folder, beside its other arms: seed0+plan, seed0+fixed
                    config.pipeline.model.plan = ARM_VARIANTS[variant]
                    config.timestamp = f"seed{seed}+{variant}"
                check_run_config(config, arm)
                label_dir = runs_dir / scene / method / config.timestamp
                specs.append(RunSpec(index=len(specs), scene=scene, method=arm, seed=seed,
                                     run_dir=label_dir.absolute(), config=config, max_steps=args.max_num_iterations,
                                     label_dir=str(label_dir)))
    return specs


def set_threads(threads: int) -> None:
    """Run this process's torch ops and numba kernels on ``threads`` threads (the environment for pools not yet
    started, the runtime setters for those that are; numba cannot go above the count its pool started with)."""
    os.environ.setdefault("OMP_NUM_THREADS", str(threads))
    os.environ.setdefault("NUMBA_NUM_THREADS", str(threads))
    import numba
    import torch

    torch.set_num_threads(threads)
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]


def choose_runner(args: argparse.Namespace):
    """The serial in-process runner (``--workers 1``, no cluster), or Ray: an embedded local cluster of
    ``--workers`` runs, or the cluster at ``--ray-address`` / ``RAY_ADDRESS``."""
    address = args.ray_address or os.environ.get("RAY_ADDRESS") or None
    if args.workers < 1:
        raise BenchArgumentError(f"--workers must be at least 1, got {args.workers}")
    if args.threads is not None and args.threads < 1:
        raise BenchArgumentError(f"--threads must be at least 1, got {args.threads}")
    if address is None and args.workers == 1:
        if args.threads is not None:
            set_threads(args.threads)
        return SerialRunner()
    threads = args.threads or (1 if address else max(1, (os.cpu_count() or 1) // args.workers))
    return RayRunner(workers=args.workers, threads=threads, address=address,
                     gpus_per_run=1 if str(args.device).startswith("cuda") else 0)


class Study:
    """The results of a study's runs as they arrive, and its report in the runs' planned order (whatever order they
    finished in), rewritten after every run trained here, so an interrupted study leaves a report of what it finished.
    A run reused as it is joins the report with the next trained run or at the end (:meth:`write_if_behind`): a
    resumed study reuses tens of runs in its first minutes, and a report per run takes a core from the training."""

    def __init__(self, specs: Sequence[RunSpec], out_dir: Path, args: argparse.Namespace):
        self.specs, self.out_dir, self.args = list(specs), out_dir, args
        self.results: dict[int, dict] = {}
        self.baseline = args.baseline if args.baseline in args.methods else None
        self.paths: dict[str, Path] = {}
        self.behind = False  # results that the written report lacks

    def add(self, result: dict) -> None:
        self.results[result["index"]] = result
        if result["status"] == "reused":
            self.behind = True
        else:
            self.write()

    def write_if_behind(self) -> None:
        if self.behind:
            self.write()

    def finished_runs(self) -> list[dict]:
        runs = []
        for spec in self.specs:
            result = self.results.get(spec.index)
            if result is None:
                continue
            runs.append({"scene": spec.scene, "method": spec.method, "seed": spec.seed,
                         "run_dir": spec.label_dir if result["run_dir"] == str(spec.run_dir) else result["run_dir"],
                         "status": result["status"], "wall_s": result["wall_s"],
                         "cpu": machine_kinds(result.get("machines", [])),
                         **({"error": result["error"]} if result.get("error") else {})})
        return runs

    def write(self) -> None:
        self.behind = False
        runs = self.finished_runs()
        atomic_write_text(self.out_dir / "runs.json", json.dumps(runs, indent=1))
        rows, lpips_note = [], None
        for run, spec in zip(runs, (s for s in self.specs if s.index in self.results)):
            records = self.results[spec.index]["records"]
            rows += eval_rows(records, spec.scene, spec.method, spec.seed, run["run_dir"], cpu=run["cpu"])
            lpips_note = lpips_note or next(
                (r.get("lpips_unavailable") for r in records if r.get("kind") == "eval" and r.get("lpips_unavailable")),
                None,
            )
        if rows:
            self.paths = write_report(rows, self.out_dir, baseline=self.baseline, time_key=self.args.time_key,
                                      lpips_note=lpips_note, also_against=self.args.also_against)
            if self.baseline:  # the paired difference at every evaluated step (docs/report.md)
                self.paths.update(write_along_training(rows, self.out_dir, self.baseline, self.args.time_key))
            self.paths.update(write_per_view(self._final_views(), self.out_dir))

    def _final_views(self) -> list[dict]:
        views = []
        for spec in self.specs:
            result = self.results.get(spec.index)
            if result is None:
                continue
            end = final_step(spec.run_dir, spec.max_steps)
            final = next((r for r in reversed(result["records"]) if r.get("kind") == "eval"
                          and r.get("step") == end), None)
            if final is None:
                continue
            for view in final.get("per_image", []):
                views.append({"scene": spec.scene, "method": spec.method, "seed": spec.seed, "step": final["step"],
                              **view})
        return views

    def failures(self) -> list[dict]:
        return [r for r in self.finished_runs() if r["status"] == "failed"]


def run_bench(args: argparse.Namespace, argv: Sequence[str]) -> dict[str, Path]:
    methods_available = discover_methods()
    check_arms(args.methods, methods_available)
    out_dir = Path(args.output_dir)
    runs_dir = Path(args.runs_dir) if args.runs_dir else out_dir / "runs"
    specs = plan_runs(args, methods_available, runs_dir)
    if args.resume or args.report_only:  # every folder of another setting refused before any run starts
        for spec in specs:
            check_same_settings(spec.run_dir, spec.config)
    if args.resume and not args.report_only:
        check_budget_reaches_checkpoints(specs)
        for spec in specs:  # what a killed run left mid-write, a finished run's too: removed, one line each
            remove_orphan_temp_files(spec.run_dir / CHECKPOINT_DIR, announce=functools.partial(_announce, spec.name))
    if args.report_only:
        to_run = [spec for spec in specs if is_finished(spec.run_dir, spec.max_steps)]
        if not to_run:
            raise BenchArgumentError(f"--report-only: none of the {len(specs)} runs is finished in {runs_dir}")
        runner: SerialRunner | RayRunner = SerialRunner()  # finished runs are only read
    else:
        to_run, runner = specs, choose_runner(args)
        if isinstance(runner, RayRunner) and not (args.ray_address or os.environ.get("RAY_ADDRESS")):
            share_memory_budget(specs, args.workers)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not args.report_only:
        (out_dir / "command.txt").write_text("kc-bench " + " ".join(shlex.quote(a) for a in argv) + "\n")
    study = Study(specs, out_dir, args)
    try:
        runner.run(to_run, study.add, resume=args.resume or args.report_only)
    finally:  # also after Ctrl-C: the report and plots of what finished
        study.write_if_behind()
        runs = [r for r in study.finished_runs() if r["status"] != "failed"]
        if runs:
            study.paths.update(write_kurtosis_gap_plots(runs, out_dir))
            study.paths.update(write_gradient_share_plots(runs, out_dir))
            study.paths.update(write_plan_table(runs, out_dir))
    paths = dict(study.paths)
    paths["command"] = out_dir / "command.txt"
    paths["runs"] = out_dir / "runs.json"
    failures = study.failures()
    if failures:
        lines = "\n".join(f"  {f['scene']} {f['method']} seed {f['seed']} ({f['run_dir']}): {f['error']}"
                          for f in failures)
        print(f"[kc-bench] {len(failures)} of {len(specs)} runs failed (the report holds the others):\n{lines}",
              file=sys.stderr, flush=True)
        raise StudyRunsFailed(len(failures))
    return paths


def share_memory_budget(specs: Sequence[RunSpec], workers: int) -> None:
    """Runs that train at once on this machine's CPU share its memory: each run left at the default budget (0: a
    share of what the process may use, engine/memory.py) gets ``1/workers`` of this machine's, since each alone would
    count the memory the others are about to fill as its own."""
    total = cpu_memory_it_may_use()
    if total is None or workers <= 1:
        return
    share = round(total * BUDGET_FRACTION / workers / 1e9, 2)
    for spec in specs:
        machine = spec.config.machine
        if machine.memory_budget_gb == 0 and str(machine.device) == "cpu":
            machine.memory_budget_gb = share


def check_budget_reaches_checkpoints(specs: Sequence[RunSpec]) -> None:
    """``--resume`` with a budget below the step a run's checkpoint already holds (a run that has no evaluation at
    that budget to be reused with) would fail in that run, after the study started: refused before any run, in one
    line naming the budget the runs reached."""
    past = []
    for spec in specs:
        checkpoints = list_checkpoints(spec.run_dir / CHECKPOINT_DIR)
        if checkpoints and checkpoint_step(checkpoints[-1]) > spec.max_steps and not is_finished(spec.run_dir,
                                                                                                 spec.max_steps):
            past.append((checkpoint_step(checkpoints[-1]), spec))
    if past:
        step, spec = max(past, key=lambda item: item[0])
        raise BenchArgumentError(
            f"--resume --max-num-iterations {spec.max_steps}: {len(past)} of the study's runs already went past that "
            f"step ({spec.label_dir or spec.run_dir} has its checkpoint at step {step}) and have no evaluation at step "
            f"{spec.max_steps} to be reused with; pass --max-num-iterations {step} (or more) to continue the study, or "
            "another --runs-dir to start one of that budget"
        )


class StudyRunsFailed(Exception):
    """Some runs failed (each was reported with its folder and error); the others finished and are reported."""

    def __init__(self, count: int):
        super().__init__(f"{count} runs failed")
        self.count = count


def write_per_view(views: Sequence[dict], out_dir: Path) -> dict[str, Path]:
    """``per_view.csv``: every run's final evaluation per test view (PSNR, SSIM, LPIPS with AlexNet and VGG16)."""
    if not views:
        return {}
    columns = {"scene": "scene", "method": "method", "seed": "seed", "step": "step", "view": "index",
               "image": "image", "psnr": "psnr", "ssim": "ssim", "lpips_alex": "lpips", "lpips_vgg": "lpips_vgg"}
    lines = [",".join(columns)]
    for view in views:
        cells = []
        for key in columns.values():
            value = view.get(key)
            text = "" if value is None else (repr(value) if isinstance(value, float) else str(value))
            cells.append(f'"{text}"' if "," in text else text)
        lines.append(",".join(cells))
    path = out_dir / "per_view.csv"
    atomic_write_text(path, "\n".join(lines) + "\n")
    return {"per_view": path}


def _lowest_seed_records(runs: Sequence[dict]):
    """Per scene (in run order): (scene, its lowest seed, {method: that run's metrics.jsonl records})."""
    for scene in dict.fromkeys(r["scene"] for r in runs):
        seed = min(r["seed"] for r in runs if r["scene"] == scene)
        records = {
            r["method"]: read_metrics(Path(r["run_dir"]) / "metrics.jsonl")
            for r in runs
            if r["scene"] == scene and r["seed"] == seed
        }
        yield scene, seed, records


def write_kurtosis_gap_plots(runs: Sequence[dict], out_dir: Path) -> dict[str, Path]:
    """Per scene, ``kurtosis_gap_<scene>.png``: the render-vs-GT band-kurtosis gap over training, one curve per
    method, for the lowest seed (see :func:`kc_splatfacto.analysis.diagnostics.plot_kurtosis_gap_comparison`)."""
    paths = {}
    for scene, seed, records in _lowest_seed_records(runs):
        try:
            paths[f"kurtosis_gap_{scene}"] = plot_kurtosis_gap_comparison(
                records, out_dir / f"kurtosis_gap_{scene}.png", title=f"{scene}, seed {seed}"
            )
        except ValueError as exc:  # runs shorter than the logging interval carry no kurtosis
            print(f"[kc-bench] no kurtosis gap plot for {scene}: {exc}", flush=True)
    return paths


def write_gradient_share_plots(runs: Sequence[dict], out_dir: Path) -> dict[str, Path]:
    """Per scene, ``gradient_shares_<scene>.png``: each loss term's image-gradient norm relative to the photometric
    term's over training, one panel per method, for the lowest seed (:func:`report.plot_gradient_shares`)."""
    paths = {}
    for scene, seed, records in _lowest_seed_records(runs):
        path = plot_gradient_shares(records, out_dir / f"gradient_shares_{scene}.png", title=f"{scene}, seed {seed}")
        if path is not None:
            paths[f"gradient_shares_{scene}"] = path
    return paths


def check_bench_args(args: argparse.Namespace) -> None:
    """Refuse, before the first run starts, budgets that would train nothing and lists that would make two runs one
    (a seed, a method or a scene name given twice); resolve ``--baseline`` (not given: ``splatfacto`` when it is
    among the methods, with a note when it is not)."""
    if args.max_num_iterations < 1:
        raise UserError(f"--max-num-iterations must be at least 1, got {args.max_num_iterations}")
    if args.steps_scale not in ("auto", "none"):
        try:
            float(args.steps_scale)
        except ValueError:
            raise UserError(f"--steps-scale must be 'none', 'auto' or a number, got {args.steps_scale!r}") from None
    if not (args.ray_address or os.environ.get("RAY_ADDRESS")):  # the runs train here: this machine's devices
        try:
            MachineConfig(device=args.device).resolve_device()
        except UserError as exc:
            raise UserError(str(exc).replace("--machine.device", "--device")) from exc
    for flag, folder, default in (("--output-dir", args.output_dir, DEFAULT_OUTPUT_DIR),
                                  ("--runs-dir", args.runs_dir, None)):
        if folder is not None:
            check_folder_can_hold(folder, path_flag(flag, folder, default), flag)
    if args.num_evals < 1:
        raise UserError(f"--num-evals must be at least 1, got {args.num_evals}")
    for flag, values in (("--seeds", args.seeds), ("--methods", args.methods)):
        twice = sorted({str(v) for v in values if values.count(v) > 1})
        if twice:
            raise UserError(f"{flag} lists {', '.join(twice)} more than once: each run would be trained twice into one "
                            "folder; give each once")
    names: dict[str, list[str]] = {}
    for data in args.data:
        names.setdefault(scene_name(data), []).append(str(data))
    clashes = {name: paths for name, paths in names.items() if len(paths) > 1}
    if clashes:
        name, paths = next(iter(clashes.items()))
        raise UserError(f"--data {' and '.join(paths)} are scenes of one name, '{name}': their runs and report rows "
                        "would be one scene's; rename a folder (or link it under another name)")
    if args.baseline is None:
        args.baseline = DEFAULT_BASELINE if DEFAULT_BASELINE in args.methods else None
        if args.baseline is None and len(args.methods) > 1:
            print(f"[kc-bench] no baseline ({DEFAULT_BASELINE} is not among --methods): the report has no paired "
                  "differences; pass --baseline METHOD for them", file=sys.stderr, flush=True)
    elif args.baseline not in args.methods:
        raise UserError(f"--baseline {args.baseline} is not among --methods ({', '.join(args.methods)})"
                        f"{did_you_mean(args.baseline, args.methods)}: add it to --methods or choose one of them")
    for reference in args.also_against:
        if reference not in args.methods:
            raise UserError(f"--also-against {reference} is not among --methods ({', '.join(args.methods)})"
                            f"{did_you_mean(reference, args.methods)}: add it to --methods or choose one of them")
        if reference == args.baseline:
            raise UserError(f"--also-against {reference} is the baseline, whose differences the report has already; "
                            "name another method")


def scene_name(data: str | Path) -> str:
    """The name a scene's runs and report rows carry: its folder's name (``demo`` for the demo scene)."""
    return "demo" if str(data) == "demo" else Path(str(data)).name


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kc-bench",
        description="Train methods x scenes x seeds under one step budget; report test quality against training time.",
    )
    parser.add_argument("--data", nargs="+", required=True, help="scene folder(s), or 'demo'")
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS),
                        help="registered method names; METHOD+plan or METHOD+fixed: that method with the scene plan "
                             "on or off (docs/plan.md)")
    parser.add_argument("--baseline", default=None,
                        help=f"method the deltas are taken against (default: {DEFAULT_BASELINE} when among --methods)")
    parser.add_argument("--also-against", nargs="+", default=[], metavar="METHOD",
                        help="further reference methods: the report also pairs every method but the baseline with "
                             "each (a third arm against the second, not only against the baseline)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--max-num-iterations", type=int, default=1000, help="the step budget of every run")
    parser.add_argument("--num-evals", type=int, default=8, help="log-spaced test evaluations per run")
    parser.add_argument("--eval-at-steps", type=int, nargs="*", default=[],
                        help="extra evaluation steps besides the log-spaced ones (e.g. 7000 in a 30000-step study)")
    parser.add_argument("--downscale-factor", type=int, nargs="+", default=None,
                        help="image downscale handed to the dataparser: one for every scene, or one per --data")
    parser.add_argument(
        "--steps-scale", default="none",
        help="'none' keeps the method's schedule (the first N steps of Splatfacto's), 'auto' = budget / 30000 "
             "(the whole schedule compressed to the budget: on sparse scenes it densifies every few steps and "
             "overfits, see docs/results/README.md), or a number",
    )
    parser.add_argument("--device", default="cpu", help="'cpu', 'cuda', or 'auto'")
    parser.add_argument("--time-key", choices=("train_s", "train_cpu_s", "elapsed_s"), default="train_s",
                        help="x axis: training seconds (evaluation excluded), their CPU seconds (what other work on "
                             "the machine barely moves), or wall clock")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="dotted config overrides applied to every run, e.g. pipeline.model.rasterizer=cpu")
    parser.add_argument("--output-dir", type=Path, default=DEFAULT_OUTPUT_DIR, help="report folder")
    parser.add_argument("--runs-dir", type=Path, default=None, help="run folders (default OUTPUT_DIR/runs)")
    parser.add_argument("--resume", action="store_true",
                        help="continue a stopped study: reuse finished runs, resume interrupted ones from their last "
                             "checkpoint (same command line plus --resume)")
    parser.add_argument("--report-only", action="store_true",
                        help="write the report of the runs already finished in the runs folder and train nothing "
                             "(command.txt is kept): a study's report while it runs elsewhere, or after a report "
                             "change")
    parser.add_argument("--steps-per-save", type=int, default=1000,
                        help="checkpoint every this many steps (what --resume continues from; 0: only at the end)")
    cluster = parser.add_argument_group("running runs at once (Ray: pip install 'kc-splatfacto[cluster]')")
    cluster.add_argument("--workers", type=int, default=1,
                         help="runs at once on an embedded local Ray cluster (1: one after another in this process)")
    cluster.add_argument("--threads", type=int, default=None,
                         help="torch/numba threads per run (default: all cores serially, cores/workers on a local "
                              "cluster, 1 on --ray-address)")
    cluster.add_argument("--ray-address", default=None,
                         help="submit every run as a task to this running Ray cluster (`ray start --head` prints "
                              "it; default: $RAY_ADDRESS)")
    return parser


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-bench``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli("kc-bench", main, argv)


def _announce(run_name: str, line: str) -> None:
    print(f"[kc-bench] {run_name}: {line}", flush=True)


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    check_bench_args(args)
    try:
        paths = run_bench(args, argv)
    except StudyRunsFailed:
        return 1
    except StudyInterrupted:
        print("[kc-bench] stopped: the finished runs and their report are kept; the same command with --resume "
              "continues", file=sys.stderr, flush=True)
        return INTERRUPTED_EXIT
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
