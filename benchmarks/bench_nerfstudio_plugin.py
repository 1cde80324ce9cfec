"""CPU time per training step: ``ns-train kc-splatfacto`` (the nerfstudio plugin) against ``kc-train kc-splatfacto``
on the same scene, in the same environment (the nerfstudio one: ``make nerfstudio-env``).

    .venv-nerfstudio/bin/python benchmarks/bench_nerfstudio_plugin.py                 # castle-P30 1/4, 100 and 600 steps
    .venv-nerfstudio/bin/python benchmarks/bench_nerfstudio_plugin.py --steps 100 1100 --repeats 3

Each tool trains the scene (``spars3r --downscale-factor 4``: 192x128 training images before step 3000) twice in a
fresh process, for the two step counts, without evaluations but the final one; the time per step is the difference
of the two wall-clock times divided by the difference of the steps, so start-up, data loading, kernel compilation
and the final evaluation and checkpoint cancel. Both step counts stay before the first refinement (step 600), so the
Gaussians are the seed points in both tools. The table gives each tool's time per step (mean over repeats, with the
spread) and the ratio to ``kc-train``, measured in the same invocation.

Run with another Python, it starts itself again in ``.venv-nerfstudio`` when that exists (``make bench`` runs every
benchmark with the project's own environment), and says so when it does not.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", REPO.parent / "shared" / "data"))
NERFSTUDIO_PYTHON = REPO / ".venv-nerfstudio" / "bin" / "python"
REEXEC_MARK = "KC_BENCH_IN_NERFSTUDIO_ENV"


def nerfstudio_python_or_exit() -> None:
    """Continue in this process if nerfstudio imports, else start again in ``.venv-nerfstudio`` (or say why not)."""
    try:
        import nerfstudio  # noqa: F401
    except ImportError:
        if NERFSTUDIO_PYTHON.is_file() and not os.environ.get(REEXEC_MARK):  # (a venv's python is a symlink to
            os.environ[REEXEC_MARK] = "1"  # the same interpreter: the mark, not the path, stops a second start)
            os.execv(str(NERFSTUDIO_PYTHON), [str(NERFSTUDIO_PYTHON), __file__, *sys.argv[1:]])
        print("bench_nerfstudio_plugin: skipped, nerfstudio is not installed (make nerfstudio-env)")
        sys.exit(0)


def commands(tool: str, steps: int, data: Path, downscale: int, out: Path) -> list[str]:
    bin_dir = Path(sys.executable).parent
    if tool == "ns-train":
        return [str(bin_dir / "ns-train"), "kc-splatfacto", "--machine.device-type", "cpu", "--vis", "tensorboard",
                "--output-dir", str(out), "--max-num-iterations", str(steps), "--steps-per-eval-image", "0",
                "--steps-per-eval-all-images", "0", "--steps-per-eval-batch", "0", "--steps-per-save", str(steps),
                "--data", str(data), "spars3r", "--downscale-factor", str(downscale)]
    return [str(bin_dir / "kc-train"), "kc-splatfacto", "--output-dir", str(out), "--max-num-iterations", str(steps),
            "--steps-per-eval-all-images", "0", "--logging.progress-bar", "False", "--data", str(data), "spars3r",
            "--downscale-factor", str(downscale)]


def wall_time(command: list[str], out: Path) -> float:
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=env, cwd=out)
    elapsed = time.perf_counter() - start
    if done.returncode != 0:
        sys.exit(f"failed: {' '.join(command)}\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}")
    return elapsed


def main() -> None:
    nerfstudio_python_or_exit()
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=SHARED_DATA / "castle-P30")
    parser.add_argument("--downscale-factor", type=int, default=4)
    parser.add_argument("--steps", type=int, nargs=2, default=[100, 600])
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    if not args.data.is_dir():
        sys.exit(f"no scene at {args.data} (set KC_SHARED_DATA to the folder holding castle-P30)")
    low, high = sorted(args.steps)
    per_step: dict[str, list[float]] = {"kc-train": [], "ns-train": []}
    with tempfile.TemporaryDirectory() as tmp:
        for tool in per_step:  # warm-up, not timed: the downscaled image cache, numba's on-disk kernel cache
            (Path(tmp) / f"warm-{tool}").mkdir()
            wall_time(commands(tool, 10, args.data, args.downscale_factor, Path(tmp) / f"warm-{tool}"),
                      Path(tmp) / f"warm-{tool}")
        for repeat in range(args.repeats):
            for tool in per_step:  # interleaved: a slow spell of the machine moves both tools
                times = {}
                for steps in (low, high):
                    out = Path(tmp) / f"{tool}-{steps}-{repeat}"
                    out.mkdir()
                    times[steps] = wall_time(commands(tool, steps, args.data, args.downscale_factor, out), out)
                per_step[tool].append((times[high] - times[low]) / (high - low))
                print(f"  {tool} repeat {repeat}: {times[low]:.1f} s ({low} steps), {times[high]:.1f} s ({high} steps)",
                      flush=True)
    base = statistics.mean(per_step["kc-train"])
    print(f"\n{args.data.name} 1/{args.downscale_factor}, steps {low}..{high}, {args.repeats} repeats, "
          f"torch threads {os.environ.get('OMP_NUM_THREADS', 'default')}\n")
    print("| tool | ms per step (mean) | min .. max | ratio to kc-train |")
    print("|---|---|---|---|")
    for tool, values in per_step.items():
        mean = statistics.mean(values)
        print(f"| {tool} kc-splatfacto | {1e3 * mean:.1f} | {1e3 * min(values):.1f} .. {1e3 * max(values):.1f} | "
              f"{mean / base:.2f}x |")


if __name__ == "__main__":
    main()
