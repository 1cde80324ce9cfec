"""torch.profiler over ordinary training steps on CUDA: where a splatfacto and a kc-splatfacto step spend host and
device time, and the device's share of the wall time.

The profiled steps are ordinary ones (``train_iteration``: no evaluation, checkpoint, logging or parameter scan; an
earlier version profiled ``train()`` through a run's last step, which evaluates every test view). ``--device cpu`` runs the same plumbing on
the CPU with tiny settings (CPU activity only, no device time): what the GPU campaign's tests check without a GPU.

    python benchmarks/profile_gpu_step.py [--scene castle-P30] [--warmup-steps 1000] [--steps 30] [--device cuda]
"""


import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
from torch.profiler import ProfilerActivity, profile  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gpu import gpu_config, ordinary_steps, synchronize  # noqa: E402
from bench_train import SHARED_DATA  # noqa: E402

from kc_splatfacto.engine.metrics_log import MetricsWriter  # noqa: E402
from kc_splatfacto.engine.trainer import Trainer  # noqa: E402

METHODS = ("splatfacto", "kc-splatfacto")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line, with what :func:`bench_gpu.gpu_config` reads besides (``device``, ``profile_phases``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=SHARED_DATA / "castle-P30")
    parser.add_argument("--downscale", type=int, default=1)
    parser.add_argument("--warmup-steps", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--rows", type=int, default=30)
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda",
                        help="cpu: the plumbing only (tiny runs on the CPU), no device time")
    args = parser.parse_args(argv)
    args.profile_phases = False  # a synchronisation after each phase would change what is profiled
    return args


def profile_method(method: str, args: argparse.Namespace, out: Path, run_dir: Path) -> dict:
    """Profile ``args.steps`` ordinary steps of ``method`` from the warm-up's state; prints the tables and returns
    {"wall_s", "device_s", "steps"}."""
    config = gpu_config(method, args, out, args.warmup_steps + 10)
    config.load_dir = run_dir / "nerfstudio_models"
    config.load_step = args.warmup_steps
    config.resume_from_other_run = True  # kc-splatfacto from splatfacto's warm-up: a new run folder
    trainer = Trainer(config)
    trainer.train()  # 10 steps: caches and kernels warm
    numbers = ordinary_steps(trainer.config.max_num_iterations, args.steps)
    trainer._writer = MetricsWriter(trainer.run_dir / "metrics.jsonl")  # train() closed its own; steps write records
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if args.device == "cuda" else [])
    try:
        synchronize(args.device)
        t0 = time.perf_counter()
        with profile(activities=activities) as prof:
            for step in numbers:
                trainer.train_iteration(step)
            synchronize(args.device)
        wall_s = time.perf_counter() - t0
    finally:
        trainer.writer.close()
    events = prof.key_averages()
    device_s = sum(getattr(e, "self_device_time_total", 0.0) for e in events) / 1e6
    print(f"\n==== {method}: {args.steps} ordinary steps, {trainer.model.num_points} Gaussians, by self CPU time")
    print(events.table(sort_by="self_cpu_time_total", row_limit=args.rows, max_name_column_width=60))
    if args.device == "cuda":
        print(f"\n==== {method}: by device time")
        print(events.table(sort_by="self_device_time_total", row_limit=15, max_name_column_width=60))
    print(f"\n==== {method}: {1000 * wall_s / args.steps:.2f} ms per step (under the profiler), device busy "
          f"{1000 * device_s / args.steps:.2f} ms per step: {100 * device_s / wall_s:.0f} % of the wall time")
    return {"wall_s": wall_s, "device_s": device_s, "steps": args.steps}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.device == "cuda" and not torch.cuda.is_available():
        print("needs CUDA (or --device cpu for the plumbing)", file=sys.stderr)
        return 1
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        warm = gpu_config("splatfacto", args, out, args.warmup_steps)
        warm.timestamp = "warmup"
        run_dir = Trainer(warm).train()
        for method in METHODS:
            profile_method(method, args, out, run_dir)
    return 0


if __name__ == "__main__":
    sys.exit(main())
