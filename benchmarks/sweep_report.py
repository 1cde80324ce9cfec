"""Report a sweep: finished run folders of one scene under labels of your choice, against one of them.

``kc-bench`` reports registered methods run with one set of overrides; a sweep varies the overrides from run to run
(``kc-bench --methods kc-splatfacto --set pipeline.model.frequency.kc_weight=1e-6 --runs-dir ...``), so its runs land in
several run folders under the same method name. This script puts them side by side::

    python benchmarks/sweep_report.py --out docs/results/castle-P30-sweep --baseline splatfacto \\
        splatfacto=outputs/study-castle-P30-7k/castle-P30/splatfacto/seed0 \\
        kc-splatfacto=outputs/study-castle-P30-7k/castle-P30/kc-splatfacto/seed0 \\
        kc-1e-6=outputs/sweep-castle-P30-7k/kc-1e-6/castle-P30/kc-splatfacto/seed0

Writes into ``--out`` what ``kc-bench`` writes for a study (``evals.csv``, ``results.md`` with the paired table,
``<metric>_vs_time.png``), plus ``settings.md``: each label's model settings that differ from the baseline's, read
from the run's own ``config.yml`` (so the table says what was trained, not what was meant), and
``gradient_shares.png`` for the labels that logged shares. Every run must be finished at the same last step, on the
same scene; runs with the same seed are paired.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from kc_splatfacto.analysis.report import eval_rows, plot_gradient_shares, write_report
from kc_splatfacto.engine.config import load_config
from kc_splatfacto.engine.metrics_log import read_metrics


def labelled_run_dir(spec: str, required: tuple[str, ...] = ("config.yml", "metrics.jsonl")) -> tuple[str, Path]:
    """``LABEL=RUN_DIR`` -> (label, run folder), the folder checked to hold ``required`` (also used by
    test_views_figure.py); anything else exits with a message naming the argument or the missing file."""
    script = Path(sys.argv[0]).stem
    label, sep, folder = spec.partition("=")
    if not sep or not label or not folder:
        raise SystemExit(f"{script}: '{spec}' is not LABEL=RUN_DIR")
    run_dir = Path(folder)
    for name in required:
        if not (run_dir / name).is_file():
            raise SystemExit(f"{script}: {run_dir / name} is missing (pass a finished kc-train/kc-bench run folder)")
    return label, run_dir


def settings_table(configs: dict[str, object], baseline: str) -> str:
    """Markdown: per label, the ``pipeline.model`` fields (and seed) that differ from the baseline's config."""
    base = dataclasses.asdict(configs[baseline].pipeline.model)
    lines = ["| label | seed | model settings that differ from `" + baseline + "` |", "|---|---|---|"]
    for label, config in configs.items():
        model = dataclasses.asdict(config.pipeline.model)
        changed = ", ".join(f"{k}={v}" for k, v in model.items() if base.get(k) != v) or "(none)"
        lines.append(f"| {label} | {config.machine.seed} | {changed} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_DIR, one per run")
    parser.add_argument("--baseline", required=True, help="the label the differences are taken against")
    parser.add_argument("--out", required=True, type=Path, help="report folder")
    args = parser.parse_args(argv)

    runs = dict(labelled_run_dir(spec) for spec in args.runs)
    if args.baseline not in runs:
        raise SystemExit(f"sweep_report: --baseline {args.baseline} is none of the labels {sorted(runs)}")
    configs = {label: load_config(run_dir / "config.yml") for label, run_dir in runs.items()}
    records = {label: read_metrics(run_dir / "metrics.jsonl") for label, run_dir in runs.items()}
    scenes = {config.experiment_name for config in configs.values()}
    if len(scenes) != 1:
        raise SystemExit(f"sweep_report: the runs are of several scenes {sorted(scenes)}; report one scene at a time")
    (scene,) = scenes

    rows = []
    for label, config in configs.items():
        run_rows = eval_rows(records[label], scene, label, config.machine.seed, runs[label])
        if not run_rows or run_rows[-1]["step"] != config.max_num_iterations:
            raise SystemExit(f"sweep_report: {runs[label]} has not finished (no evaluation at its last step "
                             f"{config.max_num_iterations})")
        rows += run_rows
    budgets = {config.max_num_iterations for config in configs.values()}
    if len(budgets) != 1:
        raise SystemExit(f"sweep_report: the runs end at different steps {sorted(budgets)}; compare equal budgets")

    paths = write_report(rows, args.out, baseline=args.baseline)
    settings = settings_table(configs, args.baseline)
    (args.out / "settings.md").write_text(settings)
    shares = plot_gradient_shares(records, args.out / "gradient_shares.png", title=scene)
    print(settings)
    print(paths["table"].read_text())
    if shares:
        print(f"gradient shares: {shares}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
