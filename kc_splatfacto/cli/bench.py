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

Example (the committed castle-P30 result)::

    kc-bench --data ../shared/data/castle-P30 --downscale-factor 4 --methods splatfacto kc-splatfacto \\
        kc-splatfacto-fine --seeds 0 1 2 --max-num-iterations 800 --num-evals 8 --steps-scale 1 \\
        --set pipeline.model.num_downscales=0 --output-dir docs/results/castle-P30 --runs-dir outputs/bench-castle-P30
"""

from __future__ import annotations


import argparse
import copy
import json
import shlex
import sys
import time
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from kc_splatfacto.engine.optimizers import SPLATFACTO_SCHEDULE_STEPS  # ``--steps-scale auto``: budget / this
from kc_splatfacto.errors import UserError


class BenchArgumentError(UserError, ValueError):
    """A kc-bench argument that cannot work (a budget below 1, a bad --set, an unknown method)."""

DEFAULT_METHODS = ("splatfacto", "kc-splatfacto")
DEFAULT_BASELINE = "splatfacto"


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
    """``config`` with one dotted field set from ``'pipeline.model.kc_weight=1e-4'``, parsed by kc-train's own
    parser (:func:`kc_splatfacto.cli.train.override_config`): the same flags, types, choices and errors as
    ``kc-train METHOD --pipeline.model.kc-weight 1e-4``. Several values (a tuple field) are separated by spaces."""
    from kc_splatfacto.cli.train import override_config

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
    from kc_splatfacto.data.detect import AutoDataParserConfig

    config = copy.deepcopy(spec_config)
    config.method_name = method
    config.experiment_name = experiment
    config.output_dir = runs_dir
    config.timestamp = f"seed{seed}"
    config.pipeline.datamanager.data = Path(data)
    config.pipeline.datamanager.dataparser = AutoDataParserConfig()  # detected from data
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


def check_same_settings(run_dir: Path, config: Any) -> None:
    """A run folder the study would reuse or continue must have been trained with the settings ``config`` asks for:
    model, seed, optimizers, scene and dataparser with its settings (e.g. the downscale factor), as its
    ``config.yml`` records them. Anything else is a :class:`BenchArgumentError` naming the folder and what differs,
    never a finished run of another setting silently reported as this one."""
    import dataclasses

    from kc_splatfacto.engine.config import load_config
    from kc_splatfacto.engine.run_guard import differences

    saved_path = run_dir / "config.yml"
    if not saved_path.is_file():
        return
    saved = load_config(saved_path)
    mismatch = [
        name for name, a, b in (
            ("pipeline.model", dataclasses.asdict(saved.pipeline.model), dataclasses.asdict(config.pipeline.model)),
            ("machine.seed", saved.machine.seed, config.machine.seed),
            ("optimizers", dataclasses.asdict(saved.optimizers), dataclasses.asdict(config.optimizers)),
        ) if a != b
    ] + differences(saved, config, parser_settings=True)
    if mismatch:
        raise BenchArgumentError(
            f"--resume: {run_dir} was trained with another {', '.join(mismatch)} than this command asks for; "
            f"rerun with the original command, or pass another --runs-dir"
        )


def resume_point(run_dir: Path, config: Any) -> Path | None:
    """Prepare an interrupted run folder for ``--resume``: the checkpoint to continue from, or None (start again).

    The folder must hold a run of the same settings (:func:`check_same_settings`). Records logged after the
    checkpoint's step are cut from ``metrics.jsonl`` (atomically), since the resumed run logs them again; without a
    checkpoint the log is moved aside to ``metrics.interrupted.jsonl`` and the run starts from scratch.
    """
    from kc_splatfacto.atomic import atomic_write_text
    from kc_splatfacto.engine.checkpoints import CHECKPOINT_DIR, CHECKPOINT_PATTERN, list_checkpoints

    check_same_settings(run_dir, config)
    log = run_dir / "metrics.jsonl"
    checkpoints = list_checkpoints(run_dir / CHECKPOINT_DIR)
    if not checkpoints:
        if log.is_file():
            log.replace(run_dir / "metrics.interrupted.jsonl")
        return None
    step = int(CHECKPOINT_PATTERN.match(checkpoints[-1].name).group(1))
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


def _finished(run_dir: Path, max_steps: int) -> bool:
    from kc_splatfacto.engine.metrics_log import read_metrics

    log = run_dir / "metrics.jsonl"
    if not log.is_file():
        return False
    try:
        records = read_metrics(log)
    except ValueError:
        return False
    return any(r.get("kind") == "eval" and int(r.get("step", -1)) == max_steps for r in records)


def run_bench(args: argparse.Namespace, argv: Sequence[str]) -> dict[str, Path]:
    from kc_splatfacto.analysis.report import eval_rows, write_report
    from kc_splatfacto.engine.metrics_log import read_metrics
    from kc_splatfacto.engine.trainer import Trainer
    from kc_splatfacto.registry import discover_methods

    methods_available = discover_methods()
    unknown = [m for m in args.methods if m not in methods_available]
    if unknown:
        raise BenchArgumentError(f"unknown method(s) {unknown}; registered: {', '.join(methods_available) or 'none'}")
    out_dir = Path(args.output_dir)
    runs_dir = Path(args.runs_dir) if args.runs_dir else out_dir / "runs"
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "command.txt").write_text("kc-bench " + " ".join(shlex.quote(a) for a in argv) + "\n")
    eval_steps = evaluation_steps(args.max_num_iterations, args.num_evals, args.eval_at_steps)
    if args.steps_scale == "auto":
        steps_scale = args.max_num_iterations / SPLATFACTO_SCHEDULE_STEPS
    elif args.steps_scale == "none":
        steps_scale = None
    else:
        steps_scale = float(args.steps_scale)
    rows: list[dict] = []
    runs: list[dict] = []
    lpips_note = None
    baseline = args.baseline if args.baseline in args.methods else None
    paths: dict[str, Path] = {}
    downscale = scene_downscale_factors(args.data, args.downscale_factor)
    # seed-major: a study stopped part-way has the same number of paired seeds on every scene
    for seed in args.seeds:
        for data in args.data:
            scene = Path(str(data)).name if str(data) != "demo" else "demo"
            for method in args.methods:
                config = build_run_config(
                    methods_available[method].config, method=method, data=Path(data), seed=seed,
                    max_steps=args.max_num_iterations, eval_steps=eval_steps, runs_dir=runs_dir,
                    experiment=scene, downscale_factor=downscale[str(data)], steps_scale=steps_scale,
                    device=args.device, overrides=args.set,
                )
                config.steps_per_save = args.steps_per_save if args.steps_per_save > 0 else args.max_num_iterations
                expected_dir = Path(runs_dir) / scene / method / f"seed{seed}"
                start = time.perf_counter()
                status = "trained"
                if args.resume and _finished(expected_dir, args.max_num_iterations):
                    check_same_settings(expected_dir, config)
                    run_dir, status = expected_dir, "reused"
                else:
                    if args.resume and expected_dir.is_dir():
                        config.load_dir = resume_point(expected_dir, config)
                        status = "resumed" if config.load_dir is not None else "restarted"
                    run_dir = Path(Trainer(config).train())
                records = read_metrics(run_dir / "metrics.jsonl")
                new_rows = eval_rows(records, scene, method, seed, run_dir)
                rows += new_rows
                lpips_note = lpips_note or next(
                    (r.get("lpips_unavailable") for r in records if r.get("kind") == "eval" and r.get("lpips_unavailable")),
                    None,
                )
                final = new_rows[-1] if new_rows else {}
                runs.append({"scene": scene, "method": method, "seed": seed, "run_dir": str(run_dir), "status": status,
                             "wall_s": time.perf_counter() - start})
                print(
                    f"[kc-bench] {scene} {method} seed {seed}: {status} in {time.perf_counter() - start:.0f}s, "
                    f"final step {final.get('step')} PSNR {final.get('psnr')} SSIM {final.get('ssim')} "
                    f"train_s {final.get('train_s')}",
                    flush=True,
                )
                (out_dir / "runs.json").write_text(json.dumps(runs, indent=1))
                paths = write_report(rows, out_dir, baseline=baseline, time_key=args.time_key, lpips_note=lpips_note)
    paths.update(write_kurtosis_gap_plots(runs, out_dir))
    paths.update(write_gradient_share_plots(runs, out_dir))
    paths["command"] = out_dir / "command.txt"
    paths["runs"] = out_dir / "runs.json"
    return paths


def _lowest_seed_records(runs: Sequence[dict]):
    """Per scene (in run order): (scene, its lowest seed, {method: that run's metrics.jsonl records})."""
    from kc_splatfacto.engine.metrics_log import read_metrics

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
    from kc_splatfacto.analysis.diagnostics import plot_kurtosis_gap_comparison

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
    from kc_splatfacto.analysis.report import plot_gradient_shares

    paths = {}
    for scene, seed, records in _lowest_seed_records(runs):
        path = plot_gradient_shares(records, out_dir / f"gradient_shares_{scene}.png", title=f"{scene}, seed {seed}")
        if path is not None:
            paths[f"gradient_shares_{scene}"] = path
    return paths


def check_bench_args(args: argparse.Namespace) -> None:
    """Refuse budgets that would train nothing, before the first run starts."""
    if args.max_num_iterations < 1:
        raise UserError(f"--max-num-iterations must be at least 1, got {args.max_num_iterations}")
    if args.num_evals < 1:
        raise UserError(f"--num-evals must be at least 1, got {args.num_evals}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kc-bench",
        description="Train methods x scenes x seeds under one step budget; report test quality against training time.",
    )
    parser.add_argument("--data", nargs="+", required=True, help="scene folder(s), or 'demo'")
    parser.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS), help="registered method names")
    parser.add_argument("--baseline", default=DEFAULT_BASELINE, help="method the deltas are taken against")
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
    parser.add_argument("--time-key", choices=("train_s", "elapsed_s"), default="train_s",
                        help="x axis: training seconds (evaluation excluded) or wall clock")
    parser.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="dotted config overrides applied to every run, e.g. pipeline.model.rasterization_backend=cpu")
    parser.add_argument("--output-dir", type=Path, default=Path("bench"), help="report folder")
    parser.add_argument("--runs-dir", type=Path, default=None, help="run folders (default OUTPUT_DIR/runs)")
    parser.add_argument("--resume", action="store_true",
                        help="continue a stopped study: reuse finished runs, resume interrupted ones from their last "
                             "checkpoint (same command line plus --resume)")
    parser.add_argument("--steps-per-save", type=int, default=1000,
                        help="checkpoint every this many steps (what --resume continues from; 0: only at the end)")
    return parser


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-bench``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    from kc_splatfacto.cli.main import run_cli

    return run_cli("kc-bench", main, argv)


def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    check_bench_args(args)
    paths = run_bench(args, argv)
    for name, path in paths.items():
        print(f"{name}: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
