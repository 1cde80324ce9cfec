"""What the KC-3DGS regularizers cost per training step, measured under identical conditions.

Short runs (no densification: the budget ends before Splatfacto's 500-step warm-up, so every method optimizes the same
number of Gaussians) of each method, interleaved A B C A B C so that machine load drifts hit every method alike. For each
run: wall seconds of the training steps (``train_s``), the process CPU seconds, and the per-phase split the trainer
measures with ``logging.profile_phases``. Ratios are against the baseline measured in the same run.

    .venv/bin/python benchmarks/bench_regularizer_cost.py [--data ../shared/data/castle-P30] [--steps 200] [--repeats 2]
"""

from __future__ import annotations

import os

import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from kc_splatfacto.cli.bench import build_run_config  # noqa: E402
from kc_splatfacto.engine.metrics_log import read_metrics  # noqa: E402
from kc_splatfacto.engine.trainer import PHASES, Trainer  # noqa: E402
from kc_splatfacto.registry import discover_methods  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "castle-P30"))
    parser.add_argument("--downscale-factor", type=int, default=4)
    parser.add_argument("--methods", nargs="+", default=["splatfacto", "kc-splatfacto", "kc-splatfacto-fine"])
    parser.add_argument("--steps", type=int, default=200, help="steps per run (keep below 500: no densification)")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    specs = discover_methods()
    results: dict[str, list[dict]] = {m: [] for m in args.methods}
    with tempfile.TemporaryDirectory() as tmp:
        for repeat in range(args.repeats):
            for method in args.methods:
                config = build_run_config(
                    specs[method].config, method=method, data=Path(args.data), seed=repeat, max_steps=args.steps,
                    eval_steps=(), runs_dir=Path(tmp), experiment="cost", downscale_factor=args.downscale_factor,
                    steps_scale=1.0, device="cpu", overrides=["pipeline.model.num_downscales=0"],
                )
                config.logging.profile_phases = True
                config.timestamp = f"{method}-r{repeat}"
                trainer = Trainer(config)
                cpu0 = time.process_time()
                run_dir = Path(trainer.train())
                cpu = time.process_time() - cpu0
                train = [r for r in read_metrics(run_dir / "metrics.jsonl") if r.get("kind") == "train"]
                steps = max(trainer.phase_steps, 1)
                results[method].append(
                    {
                        "train_ms": 1000 * train[-1]["train_s"] / args.steps,
                        "cpu_ms": 1000 * cpu / args.steps,  # includes set-up and the final evaluation
                        **{f"{p}_ms": 1000 * trainer.phase_times[p] / steps for p in PHASES},
                        "gaussians": train[-1].get("gaussian_count"),
                    }
                )
                print(f"  {method} repeat {repeat}: {results[method][-1]['train_ms']:.1f} ms/step", flush=True)
    base = args.methods[0]
    columns = ["train_ms", "cpu_ms", *[f"{p}_ms" for p in PHASES]]
    print(f"\nper-step cost, mean over {args.repeats} interleaved runs of {args.steps} steps "
          f"({Path(args.data).name}, downscale {args.downscale_factor}); ratio vs {base}")
    print("| method | gaussians | " + " | ".join(columns) + " | train ratio | cpu ratio |")
    print("|---|---|" + "---|" * (len(columns) + 2))
    mean = {m: {c: float(np.mean([r[c] for r in results[m]])) for c in columns} for m in args.methods}
    for method in args.methods:
        cells = " | ".join(f"{mean[method][c]:.1f}" for c in columns)
        ratio = mean[method]["train_ms"] / mean[base]["train_ms"]
        cpu_ratio = mean[method]["cpu_ms"] / mean[base]["cpu_ms"]
        print(f"| {method} | {results[method][-1]['gaussians']} | {cells} | {ratio:.2f}x | {cpu_ratio:.2f}x |")


if __name__ == "__main__":
    main()
