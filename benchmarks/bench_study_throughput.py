"""Study throughput: the same runs one at a time with all threads, and as parallel Ray workers with fewer threads each.

    .venv/bin/python benchmarks/bench_study_throughput.py                       # castle-P30 1/4, 4 runs of 1500 steps
    .venv/bin/python benchmarks/bench_study_throughput.py --steps 7000 --seeds 0 1 2 3

Each layout runs ``kc-bench`` in a fresh process on the same (scene, method, seed) runs, in a temporary folder, and
the table gives the wall-clock time of the whole study, runs per hour, and the ratio to the first layout (measured in
the same invocation, so machine noise moves both), and the largest difference of a final PSNR between the layouts
(the same runs: float32 rounding of the evaluation only). Pick the faster layout for a study on this machine (``docs/study.md``).
"""

from __future__ import annotations

import argparse
import csv
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
CLOCKS = ("elapsed_s", "train_s", "train_cpu_s", "run_dir")


def run_study(out: Path, args: argparse.Namespace, workers: int, threads: int) -> float:
    command = [
        sys.executable, "-m", "kc_splatfacto.cli.bench", "--data", str(args.data), "--downscale-factor",
        str(args.downscale_factor), "--methods", *args.methods, "--seeds", *map(str, args.seeds),
        "--max-num-iterations", str(args.steps), "--num-evals", "2", "--steps-per-save", str(args.steps),
        "--output-dir", str(out), "--workers", str(workers), "--threads", str(threads),
    ]
    env = {**os.environ, "OMP_NUM_THREADS": str(threads), "NUMBA_NUM_THREADS": str(threads),
           "OMP_WAIT_POLICY": "PASSIVE"}
    start = time.perf_counter()
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        sys.exit(f"kc-bench failed ({workers} workers x {threads} threads):\n{done.stderr[-3000:]}")
    return elapsed


def evaluations(out: Path) -> list[dict]:
    with (out / "evals.csv").open() as handle:
        return [{k: v for k, v in row.items() if k not in CLOCKS} for row in csv.DictReader(handle)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=SHARED_DATA / "castle-P30")
    parser.add_argument("--downscale-factor", type=int, default=4)
    parser.add_argument("--methods", nargs="+", default=["splatfacto", "kc-splatfacto"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--cores", type=int, default=os.cpu_count() or 1)
    args = parser.parse_args()
    if not args.data.is_dir():
        sys.exit(f"no scene at {args.data} (set KC_SHARED_DATA to the folder holding castle-P30)")

    layouts = [(1, args.cores), (args.cores, 1)]  # (workers, threads per run)
    runs = len(args.methods) * len(args.seeds)
    rows, finals = [], []
    with tempfile.TemporaryDirectory(prefix="kc-throughput-") as tmp:
        for workers, threads in layouts:
            out = Path(tmp) / f"w{workers}t{threads}"
            seconds = run_study(out, args, workers, threads)
            finals.append({(r["method"], r["seed"]): float(r["psnr"]) for r in evaluations(out)
                           if int(r["step"]) == args.steps})
            rows.append((workers, threads, seconds))
            print(f"  {workers} worker(s) x {threads} thread(s): {seconds:.0f} s", file=sys.stderr, flush=True)
    base = rows[0][2]
    print(f"\n{runs} runs ({', '.join(args.methods)}; seeds {' '.join(map(str, args.seeds))}) of {args.steps} steps, "
          f"{args.data.name} at 1/{args.downscale_factor}, {args.cores} cores\n")
    print("| layout | wall-clock (s) | runs per hour | time vs one run at a time |")
    print("|---|---|---|---|")
    for workers, threads, seconds in rows:
        print(f"| {workers} worker(s) x {threads} thread(s) | {seconds:.0f} | {3600 * runs / seconds:.1f} | "
              f"{seconds / base:.2f}x |")
    # the same runs: the final PSNRs agree up to the evaluation's float32 rounding (threads change sum order)
    spread = max(abs(finals[0][k] - finals[1][k]) for k in finals[0])
    print(f"\nlargest final-PSNR difference between the layouts: {spread:.2e} dB")


if __name__ == "__main__":
    main()
