"""Whole-run hash: train a method for a number of steps and hash every Gaussian parameter and the density-control
statistics at the end, so a change that must keep training bit-identical (a refactor, a faster kernel) can be
checked, and a long study can check that the numerics it runs on have not moved before it resumes.

    .venv/bin/python benchmarks/run_hash.py --method splatfacto --steps 1200
    .venv/bin/python benchmarks/run_hash.py --method kc-splatfacto --steps 3500   # through the reset at 3000

The run is castle-P30 at 1/4 resolution (192x128), seed 0, Splatfacto's real schedule (the study's settings), on the
CPU, in a temporary folder. Prints one line: ``<method> <steps> steps <threads> threads: <16 hex digits>
(<Gaussians> Gaussians, <seconds> s) on <CPU kind>`` (the hash depends on the kind: LLVM's CPU name and its vector
features, :func:`kc_splatfacto.study.machine.cpu_kind`). The reference hashes of the current numerics are in docs/training.md.
"""

import argparse
import os
import sys

if __name__ == "__main__":  # the thread count must be in the environment before torch and numba load
    _threads = argparse.ArgumentParser(add_help=False)
    _threads.add_argument("--threads", type=int, default=None)
    _known, _ = _threads.parse_known_args()
    if _known.threads:
        os.environ["OMP_NUM_THREADS"] = os.environ["NUMBA_NUM_THREADS"] = str(_known.threads)

import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

import copy  # noqa: E402
import hashlib  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from kc_splatfacto.cli.main import INTERRUPTED_EXIT  # noqa: E402
from kc_splatfacto.engine.trainer import Trainer  # noqa: E402
from kc_splatfacto.registry import discover_methods  # noqa: E402
from kc_splatfacto.study.machine import machine_signature  # noqa: E402

SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def state_hash(trainer: Trainer) -> str:
    """sha256 (first 16 hex digits) over the Gaussian parameters and the density-control statistics, by name."""
    digest = hashlib.sha256()
    tensors = {f"param.{k}": v for k, v in trainer.model.gauss_params.items()}
    strategy_state = trainer.state.strategy_state
    tensors.update({f"strategy.{k}": v for k, v in strategy_state.items() if isinstance(v, torch.Tensor)})
    for name in sorted(tensors):
        value = tensors[name].detach().cpu().contiguous()
        digest.update(name.encode())
        digest.update(str(tuple(value.shape)).encode())
        digest.update(value.numpy().tobytes())
    return digest.hexdigest()[:16]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", default="splatfacto")
    parser.add_argument("--steps", type=int, default=1200)
    parser.add_argument("--scene", type=Path, default=SHARED_DATA / "castle-P30")
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plan", choices=("off", "on"), default="off",
                        help="the scene plan (default off: the fixed settings, whose hashes docs/training.md lists)")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch and numba threads (set in the environment before they load; default: all cores)")
    args = parser.parse_args()
    if not args.scene.is_dir():
        print(f"scene {args.scene} not found (set KC_SHARED_DATA to the shared/data folder)", file=sys.stderr)
        return 1
    methods = discover_methods()
    if args.method not in methods:
        print(f"unknown method {args.method}; registered: {', '.join(methods)}", file=sys.stderr)
        return 1
    config = copy.deepcopy(methods[args.method].config)
    config.pipeline.datamanager.set_scene(args.scene)
    config.pipeline.datamanager.dataparser.downscale_factor = args.downscale
    config.max_num_iterations = args.steps
    config.steps_per_eval_all_images = 0
    config.steps_per_save = 10**9
    config.logging.progress_bar = False
    config.machine.seed = args.seed
    config.machine.device = "cpu"
    config.pipeline.model.plan = args.plan
    with tempfile.TemporaryDirectory() as tmp:
        config.output_dir = Path(tmp)
        t0 = time.perf_counter()
        trainer = Trainer(config)
        trainer.train()
        seconds = time.perf_counter() - t0
        if trainer.interrupted:  # a part-run's state hashed under the asked step count would be a wrong reference
            print(f"{args.method}: stopped before step {args.steps} (Ctrl-C or SIGTERM): no hash; run it again",
                  file=sys.stderr)
            return INTERRUPTED_EXIT
        print(f"{args.method} {args.steps} steps {torch.get_num_threads()} threads: {state_hash(trainer)} "
              f"({trainer.model.num_points} Gaussians, {seconds:.0f} s) on {machine_signature()['kind']}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
