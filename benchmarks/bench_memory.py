"""Peak memory (RSS) of a CPU training against the number of Gaussians, at two image sizes.

Each point is its own process (peak RSS is per process): kc-splatfacto on the generated demo scene at the given image
size, started from N random Gaussians with growth off (warm-up past the budget, cap N), trained a few steps; the
process reports its RSS after set-up and its peak RSS (``ru_maxrss``). The table gives the peak, and per image size
the least-squares slope of the peak against N: the bytes each Gaussian costs at that size (parameters, gradients,
Adam's two moments, the projection's per-Gaussian buffers, the tile intersections it makes), which
``kc_splatfacto.engine.memory`` uses to check a run's ``max_num_gaussians`` against the memory it has.

    .venv/bin/python benchmarks/bench_memory.py [--gaussians 100000 300000 600000] [--sizes 320x240 960x720]
        [--steps 3]
"""

import kc_splatfacto  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import copy  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from kc_splatfacto.data.demo import DemoDataParserConfig  # noqa: E402
from kc_splatfacto.engine.memory import current_rss_bytes  # noqa: E402
from kc_splatfacto.engine.trainer import Trainer  # noqa: E402
from kc_splatfacto.registry import discover_methods  # noqa: E402

METHOD = "kc-splatfacto"
NUM_CAMERAS = 8


def one_point(gaussians: int, width: int, height: int, steps: int) -> dict:
    """Train ``steps`` steps from ``gaussians`` random Gaussians at ``width`` x ``height``; RSS after set-up, peak."""
    config = copy.deepcopy(discover_methods()[METHOD].config)
    config.pipeline.datamanager.dataparser = DemoDataParserConfig(width=width, height=height, num_cameras=NUM_CAMERAS)
    config.output_dir = Path(tempfile.mkdtemp(prefix="bench-memory-"))
    config.max_num_iterations = steps
    config.steps_per_eval_all_images = 0
    config.final_lpips_nets = ()
    config.steps_per_save = 10**9
    config.logging.progress_bar = False
    config.logging.steps_per_gradient_shares = 0
    config.machine.device = "cpu"
    config.machine.memory_budget_gb = 0.0
    model = config.pipeline.model
    model.random_init = True
    model.num_random = gaussians
    model.max_num_gaussians = gaussians
    model.num_downscales = 0
    model.warmup_length = 10 * steps  # no density control within the run: N stays N
    trainer = Trainer(config)
    trainer.setup()
    after_setup = current_rss_bytes()
    trainer.train()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # kilobytes on Linux
    return {"gaussians": trainer.model.num_points, "width": width, "height": height, "setup_rss": after_setup,
            "peak_rss": peak}


def measure(gaussians: int, width: int, height: int, steps: int) -> dict:
    out = subprocess.run([sys.executable, __file__, "--one", str(gaussians), f"{width}x{height}", str(steps)],
                         capture_output=True, text=True, check=False)
    if out.returncode != 0:
        raise SystemExit(f"the point N={gaussians} at {width}x{height} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--gaussians", type=int, nargs="+", default=[100_000, 300_000, 600_000])
    parser.add_argument("--sizes", nargs="+", default=["320x240", "960x720"])
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--one", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        gaussians, size, steps = args.one
        width, height = map(int, size.split("x"))
        print(json.dumps(one_point(int(gaussians), width, height, int(steps))))
        return
    print("| image | Gaussians | RSS after set-up (MB) | peak RSS (MB) |\n|---|---:|---:|---:|", flush=True)
    slopes = {}
    for size in args.sizes:
        width, height = map(int, size.split("x"))
        points = [measure(n, width, height, args.steps) for n in args.gaussians]
        for p in points:
            print(f"| {width}x{height} | {p['gaussians']:,} | {p['setup_rss'] / 1e6:,.0f} | {p['peak_rss'] / 1e6:,.0f} |",
                  flush=True)
        n = np.array([p["gaussians"] for p in points], float)
        peak = np.array([p["peak_rss"] for p in points], float)
        slope, intercept = np.polyfit(n, peak, 1)
        slopes[size] = (slope, intercept)
    print("\n| image | bytes per Gaussian (slope of the peak) | peak at N = 0 (intercept, MB) | peak per million Gaussians "
          "(GB) |\n|---|---:|---:|---:|")
    for size, (slope, intercept) in slopes.items():
        print(f"| {size} | {slope:,.0f} | {intercept / 1e6:,.0f} | {slope * 1e6 / 1e9:.2f} |")


if __name__ == "__main__":
    main()
