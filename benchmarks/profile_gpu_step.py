"""torch.profiler over training steps on CUDA: where a splatfacto and a kc-splatfacto step spend host and device time.

    python benchmarks/profile_gpu_step.py [--scene castle-P30] [--warmup-steps 1000] [--steps 30]
"""

import os

import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402
from torch.profiler import ProfilerActivity, profile  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_gpu import gpu_config  # noqa: E402
from bench_train import SHARED_DATA  # noqa: E402

from kc_splatfacto.engine.trainer import Trainer  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=SHARED_DATA / "castle-P30")
    parser.add_argument("--downscale", type=int, default=1)
    parser.add_argument("--warmup-steps", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--rows", type=int, default=30)
    args = parser.parse_args()
    args.profile_phases = False
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        warm = gpu_config("splatfacto", args, out, args.warmup_steps)
        warm.timestamp = "warmup"
        run_dir = Trainer(warm).train()
        for method in ("splatfacto", "kc-splatfacto"):
            config = gpu_config(method, args, out, args.warmup_steps + 10)
            config.load_dir = run_dir / "nerfstudio_models"
            config.load_step = args.warmup_steps
            config.resume_from_other_run = True  # kc-splatfacto from splatfacto's warm-up: a new run folder
            trainer = Trainer(config)
            trainer.train()  # 10 steps: caches and kernels warm
            trainer.config.max_num_iterations = args.warmup_steps + 10 + args.steps
            trainer.start_step = args.warmup_steps + 10
            with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                trainer.train()
                torch.cuda.synchronize()
            print(f"\n==== {method}: {args.steps} steps, {trainer.model.num_points} Gaussians, by self CPU time")
            print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.rows, max_name_column_width=60))
            print(f"\n==== {method}: by device time")
            print(prof.key_averages().table(sort_by="self_device_time_total", row_limit=15, max_name_column_width=60))
    return 0


if __name__ == "__main__":
    sys.exit(main())
