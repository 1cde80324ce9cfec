"""Time per training step, split into render / losses / backward / optimizer / density control, for splatfacto and
kc-splatfacto on castle-P30 at 1/4 resolution (192x128 from the stored 768x512).

Both methods start from the SAME densified state (a splatfacto warm-up run's checkpoint) and run the same number of
steps with growth capped at that state's Gaussian count, so the only difference is the loss. Rounds alternate
(splatfacto, kc, splatfacto, kc, ...) and the median per phase is reported, which tames a shared machine's noise.
Target: a kc-splatfacto step at most 1.10x a splatfacto step.

    .venv/bin/python benchmarks/bench_train.py [--rounds 3] [--steps 60] [--warmup-steps 300] [--downscale 4]
        [--methods splatfacto kc-splatfacto kc-splatfacto-corr] [--warmup-from RUN_DIR]

``--warmup-from`` starts every method from an existing splatfacto run's last checkpoint instead of a fresh warm-up:
the way to time two code versions at the SAME state (a run of another version trains a different state, e.g. 69.5k
against 79k Gaussians between two code versions, because their float rounding differs).

``--methods`` names the registered methods to time (the first is the baseline of the ratios; default splatfacto and
kc-splatfacto); the target line is printed for every method after the first.
"""

import os

import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import copy  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from kc_splatfacto.engine.trainer import PHASES, Trainer  # noqa: E402
from kc_splatfacto.registry import discover_methods  # noqa: E402

SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
TARGET_RATIO = 1.10


def make_config(method: str, scene: Path, out: Path, downscale: int, iterations: int, steps_scale: float):
    config = copy.deepcopy(discover_methods()[method].config)
    config.pipeline.datamanager.set_scene(scene)
    config.pipeline.datamanager.dataparser.downscale_factor = downscale
    config.output_dir = out
    config.experiment_name = "bench"
    config.max_num_iterations = iterations
    config.steps_per_eval_all_images = 0
    config.steps_per_save = 10**9
    config.save_only_latest_checkpoint = False
    config.logging.progress_bar = False
    config.logging.steps_per_log = 10**9  # no logging-step extras (kurtosis) inside the timed steps
    config.logging.profile_phases = True
    config.machine.device = "cpu"
    config.pipeline.model.steps_scale = steps_scale
    return config


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=SHARED_DATA / "castle-P30")
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--warmup-steps", type=int, default=300)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps-scale", type=float, default=0.1)
    parser.add_argument("--warmup-from", type=Path, default=None,
                        help="a splatfacto run folder (holding nerfstudio_models/) to start from instead of a warm-up")
    parser.add_argument("--methods", nargs="+", default=["splatfacto", "kc-splatfacto"],
                        help="registered methods; the first is the ratios' baseline")
    args = parser.parse_args()
    registered = discover_methods()
    unknown = [m for m in args.methods if m not in registered]
    if unknown:
        print(f"unknown method(s) {unknown}; registered: {', '.join(registered)}", file=sys.stderr)
        return 1
    if not args.scene.is_dir():
        print(f"scene {args.scene} not found (set KC_SHARED_DATA to the shared/data folder)", file=sys.stderr)
        return 1
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        warm = make_config("splatfacto", args.scene, out, args.downscale, args.warmup_steps, args.steps_scale)
        warm.timestamp = "warmup"
        t0 = time.perf_counter()
        if args.warmup_from is not None:
            checkpoints = sorted((args.warmup_from / "nerfstudio_models").glob("step-*.ckpt"))
            if not checkpoints or not (args.warmup_from / "config.yml").is_file():
                print(f"no config.yml and checkpoint in {args.warmup_from}: give a splatfacto run's folder",
                      file=sys.stderr)
                return 1
            # a copy: the timed runs resume the run they load (same config), so they write checkpoints into it
            run_dir = out / "warmup-source"
            (run_dir / "nerfstudio_models").mkdir(parents=True)
            shutil.copy2(args.warmup_from / "config.yml", run_dir / "config.yml")
            shutil.copy2(checkpoints[-1], run_dir / "nerfstudio_models" / checkpoints[-1].name)
            args.warmup_steps = int(checkpoints[-1].stem.split("-")[1])
            warm.max_num_iterations = args.warmup_steps
            warm.load_dir = run_dir / "nerfstudio_models"
            warm_trainer = Trainer(warm)
            warm_trainer.setup()  # loads the checkpoint: the state every method starts from
            source = f"loaded from {checkpoints[-1]}"
        else:
            warm_trainer = Trainer(warm)
            run_dir = warm_trainer.train()
            source = f"splatfacto {args.warmup_steps} steps"
        n_gaussians = warm_trainer.model.num_points
        height, width = warm_trainer.datamanager.train_dataset.image_uint8(0).shape[:2]
        print(f"warm-up: {source} -> {n_gaussians} Gaussians at {width}x{height} "
              f"in {time.perf_counter() - t0:.1f} s")
        per_method: dict[str, dict[str, list[float]]] = {m: {p: [] for p in PHASES + ("step",)}
                                                        for m in args.methods}
        for _ in range(args.rounds):
            for method in per_method:
                config = make_config(method, args.scene, out, args.downscale, args.warmup_steps + args.steps,
                                     args.steps_scale)
                config.load_dir = run_dir / "nerfstudio_models"
                config.load_step = args.warmup_steps
                config.resume_from_other_run = True  # every method starts from the warm-up run, in a new folder
                config.pipeline.model.max_num_gaussians = n_gaussians
                trainer = Trainer(config)
                trainer.setup()
                # the first step builds the GT wavelet caches and warms kernels: time the steps after it
                trainer.config.max_num_iterations = args.warmup_steps + 1
                trainer.train()
                trainer.phase_times = {p: 0.0 for p in PHASES}
                trainer.phase_steps = 0
                trainer.config.max_num_iterations = args.warmup_steps + args.steps
                trainer.start_step = args.warmup_steps + 1
                t_train = trainer.train_seconds
                trainer.train()
                steps = trainer.phase_steps
                for phase in PHASES:
                    per_method[method][phase].append(1000 * trainer.phase_times[phase] / steps)
                per_method[method]["step"].append(1000 * (trainer.train_seconds - t_train) / steps)
    median = {m: {p: statistics.median(v) for p, v in d.items()} for m, d in per_method.items()}
    base = median[args.methods[0]]
    print(f"\nms per step (median of {args.rounds} rounds x {args.steps} steps; castle-P30 {width}x{height}, "
          f"{n_gaussians} Gaussians, {torch.get_num_threads()} threads)\n")
    header = "| method | " + " | ".join(PHASES) + " | step | ratio |"
    print(header)
    print("|" + "---|" * (len(PHASES) + 3))
    for method, values in median.items():
        cells = " | ".join(f"{values[p]:.1f}" for p in PHASES)
        print(f"| {method} | {cells} | {values['step']:.1f} | {values['step'] / base['step']:.3f}x |")
    print()
    for method in args.methods[1:]:
        ratio = median[method]["step"] / base["step"]
        print(f"{method} / {args.methods[0]} step time: {ratio:.3f}x (target <= {TARGET_RATIO:.2f}x): "
              f"{'met' if ratio <= TARGET_RATIO else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
