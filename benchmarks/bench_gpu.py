"""GPU step time: splatfacto and kc-splatfacto through ``kc-train``'s Trainer on CUDA (gsplat backend), against a
minimal gsplat ``examples/simple_trainer.py``-style loop (gsplat.rasterization, 0.8 L1 + 0.2 D-SSIM, one Adam per
parameter, no density control, no checks) from the SAME Gaussians.

All three start from one warm-up checkpoint (splatfacto, real schedule, training resolution fixed at the full image
size), growth capped at its Gaussian count. Rounds alternate methods; medians are reported. Needs CUDA and gsplat;
prints a table (ms per step) and the kc/splatfacto ratio (target <= 1.10x).

``--count-syncs`` adds, per method, the host synchronisations of a training step (CUDA: torch's sync debug mode,
which warns at each synchronising call) and the kernel launches (the profiler's ``cudaLaunchKernel`` calls), counted
over a few ordinary steps after the timed ones, and lists the synchronisations by source line (``path:line
function`` of the innermost package frame, ``host_syncs.source_of``: the same attribution as the CPU-side detector
of benchmarks/host_syncs.py, so the two lists compare line by line). ``--device cpu`` runs the same plumbing on the
CPU (our rasterizer in the simple loop; the synchronisations are the CPU-side detector's, on the torch path; no
launch counts): the GPU campaign's dry run (benchmarks/gpu_campaign.py).

    python benchmarks/bench_gpu.py [--scene castle-P30] [--downscale 1] [--warmup-steps 3000] [--steps 200] [--rounds 3]
        [--device cuda] [--count-syncs]
"""


import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
from collections import Counter  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_train import SHARED_DATA, TARGET_RATIO, make_config  # noqa: E402
from host_syncs import count_ordinary_steps, source_of  # noqa: E402

from kc_splatfacto.engine.metrics_log import MetricsWriter  # noqa: E402
from kc_splatfacto.engine.trainer import PHASES, Trainer  # noqa: E402
from kc_splatfacto.engine.training_state import PARAMETER_SCAN_EVERY  # noqa: E402


def gpu_config(method, args, out, iterations):
    config = make_config(method, args.scene, out, args.downscale, iterations, 1.0)
    config.machine.device = args.device
    config.pipeline.model.num_downscales = 0  # time every step at the full image size
    config.logging.profile_phases = args.profile_phases
    return config


def synchronize(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


LAUNCH_EVENTS = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx")


def count_syncs_and_launches(run_steps, steps: int) -> dict:
    """Host synchronisations (torch's sync debug mode warns at each) and kernel launches (the profiler's launch
    calls) per step while ``run_steps()`` takes ``steps`` steps on CUDA; ``sources``: the synchronisations per step
    by where they come from (:func:`host_syncs.source_of`, else the warning's own file and line)."""
    from torch.profiler import ProfilerActivity, profile

    sources: Counter = Counter()

    def record(message, category, filename, lineno, file=None, line=None):  # noqa: ARG001
        # called while the synchronising call returns to Python (torch turns its C++ warning into a Python one
        # there), so the stack is the caller's
        if "synchroniz" in str(message).lower():
            sources[source_of(sys._getframe(1)) or f"{filename}:{lineno}"] += 1

    with warnings.catch_warnings():  # restores showwarning on the way out
        warnings.simplefilter("always")
        warnings.showwarning = record
        torch.cuda.set_sync_debug_mode("warn")
        try:
            with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                run_steps()
                torch.cuda.synchronize()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    launches = sum(e.count for e in prof.key_averages() if e.key in LAUNCH_EVENTS)
    return {"syncs": sum(sources.values()) / steps, "launches": launches / steps,
            "sources": {k: v / steps for k, v in sources.items()}}


def ordinary_steps(first: int, steps: int) -> list[int]:
    """``steps`` step numbers from ``first`` on that are no parameter-scan step (every PARAMETER_SCAN_EVERY)."""
    out = []
    step = first
    while len(out) < steps:
        if step % PARAMETER_SCAN_EVERY:
            out.append(step)
        step += 1
    return out


def trainer_syncs(trainer, args, steps: int = 5) -> dict:
    """:func:`count_syncs_and_launches` of ``steps`` ordinary training steps of our trainer (``train_iteration``: no
    evaluation, checkpoint, logging or parameter scan among them). On the CPU the synchronisations are the CPU-side
    detector's on the torch path (``host_syncs.count_ordinary_steps``, one more step taken first to fill the torch
    path's caches), the rasterizer's left out (gsplat's on CUDA); no launch count.

    The first campaign (2026-11-28) counted ``trainer.train()`` over 5 steps ending at its last step, whose evaluation
    of every test image and checkpoint were counted with them: 54 and 25 "per step" on castle-P30 and fern-12."""
    trainer._writer = MetricsWriter(trainer.run_dir / "metrics.jsonl")  # train() closed its own; steps write records
    try:
        if args.device != "cuda":
            numbers = ordinary_steps(trainer.config.max_num_iterations, steps + 1)
            found = count_ordinary_steps(trainer, numbers, warm=1)
            sources = Counter()
            for (kind, where), n in found.ours().items():
                sources[f"{where} [{kind}]"] += n / steps
            return {"syncs": sum(sources.values()), "launches": float("nan"), "sources": dict(sources)}
        numbers = ordinary_steps(trainer.config.max_num_iterations, steps)
        return count_syncs_and_launches(lambda: [trainer.train_iteration(s) for s in numbers], steps)
    finally:
        trainer.writer.close()


VARIANTS = {
    "splatfacto": ("splatfacto", {}),
    "kc-splatfacto": ("kc-splatfacto", {}),
    # the same methods with the image-space loss eager (no CUDA graph), and kc's terms also level by level (the
    # path before the fused Function): what each of the two brings
    "splatfacto, eager loss": ("splatfacto", {"graphs": False}),
    "kc-splatfacto, eager loss": ("kc-splatfacto", {"graphs": False}),
    "kc-splatfacto, eager, level by level": ("kc-splatfacto", {"graphs": False, "fused": False}),
}
"""the rows of the table: (method, how the loss runs)"""


LOOP_TARGET = 0.6
"""our splatfacto step against the gsplat-style loop's"""


def timed_method(method, args, out, run_dir, n_gaussians, graphs: bool = True, fused: bool = True):
    config = gpu_config(method, args, out, args.warmup_steps + args.steps)
    config.pipeline.model.loss_cuda_graphs = graphs
    config.load_dir = run_dir / "nerfstudio_models"
    config.load_step = args.warmup_steps
    config.pipeline.model.max_num_gaussians = n_gaussians
    config.resume_from_other_run = True  # other settings (and methods) than the warm-up run's: a new run folder
    trainer = Trainer(config)
    trainer.setup()
    if trainer.model.frequency_loss is not None:
        trainer.model.frequency_loss.fused = fused
    trainer.config.max_num_iterations = args.warmup_steps + 10  # GT caches, kernels, allocator warm
    trainer.train()
    trainer.phase_times = {p: 0.0 for p in PHASES}
    trainer.phase_steps = 0
    trainer.config.max_num_iterations = args.warmup_steps + 10 + args.steps
    trainer.start_step = args.warmup_steps + 10
    synchronize(args.device)
    t0 = time.perf_counter()
    trainer.train()
    synchronize(args.device)
    steps = trainer.phase_steps
    row = {p: 1000 * trainer.phase_times[p] / steps for p in PHASES}
    row["step"] = 1000 * (time.perf_counter() - t0) / steps
    row["gaussians"] = trainer.model.num_points
    if args.count_syncs:
        row.update(trainer_syncs(trainer, args))
    return row


def reference_loop(args, state, dataset, steps):
    """gsplat simple_trainer-style: rasterization + 0.8 L1 + 0.2 (1 - SSIM) + Adam, no density control. On the CPU
    (the dry run) our gsplat-compatible ``rasterization()`` stands in for gsplat's."""
    from kornia.metrics import ssim as kornia_ssim

    if args.device == "cuda":
        from gsplat import rasterization
    else:
        from kc_splatfacto.render.rasterization import rasterization
    device = torch.device(args.device)
    params = {k: torch.nn.Parameter(v.detach().clone().to(device)) for k, v in state.items()}
    lrs = {"means": 1.6e-4, "scales": 5e-3, "quats": 1e-3, "opacities": 5e-2, "features_dc": 2.5e-3,
           "features_rest": 2.5e-3 / 20}
    optimizers = {k: torch.optim.Adam([params[k]], lr=lr, eps=1e-15) for k, lr in lrs.items()}
    cams = [dataset.cameras[i] for i in range(len(dataset))]
    images = [torch.as_tensor(dataset.image_uint8(i)).to(device).float() / 255.0 for i in range(len(dataset))]
    viewmats = [c.viewmats.float().to(device) for c in cams]
    Ks = [c.Ks.float().to(device) for c in cams]
    height, width = images[0].shape[:2]

    def one(i):
        colors = torch.cat([params["features_dc"][:, None, :], params["features_rest"]], dim=1)
        render, _, _ = rasterization(
            params["means"], params["quats"], torch.exp(params["scales"]),
            torch.sigmoid(params["opacities"]).squeeze(-1), colors, viewmats[i], Ks[i], width, height,
            sh_degree=3, absgrad=True)
        gt = images[i]
        l1 = (render[0] - gt).abs().mean()
        ssim = kornia_ssim(render[0].permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None], 11).mean()
        loss = 0.8 * l1 + 0.2 * (1 - ssim)
        loss.backward()
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)

    for s in range(10):
        one(s % len(images))
    synchronize(args.device)
    t0 = time.perf_counter()
    for s in range(steps):
        one(s % len(images))
    synchronize(args.device)
    row = {"step": 1000 * (time.perf_counter() - t0) / steps, "gaussians": params["means"].shape[0]}
    if args.count_syncs and args.device == "cuda":
        row.update(count_syncs_and_launches(lambda: [one(s % len(images)) for s in range(5)], 5))
    elif args.count_syncs:
        row.update(syncs=float("nan"), launches=float("nan"), sources={})
    return row


def print_sync_sources(rows: dict[str, list[dict]], counted_by: str) -> None:
    """Each method's synchronisations per ordinary step by source (its last round), most frequent first."""
    print(f"\nhost synchronisations per step by source ({counted_by}):")
    for method, rounds in rows.items():
        sources = rounds[-1].get("sources") or {}
        print(f"  {method}: {sum(sources.values()):.1f}" + ("" if sources else " (none, or not counted here)"))
        for where, n in sorted(sources.items(), key=lambda kv: (-kv[1], kv[0])):
            print(f"    {n:6.2f}  {where}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=SHARED_DATA / "castle-P30")
    parser.add_argument("--downscale", type=int, default=1)
    parser.add_argument("--warmup-steps", type=int, default=3000)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--profile-phases", action="store_true", help="synchronise after each phase (per-phase table)")
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda",
                        help="cpu: the plumbing only (the GPU campaign's dry run), no meaningful times")
    parser.add_argument("--count-syncs", action="store_true",
                        help="host synchronisations and kernel launches per step (CUDA)")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        print("needs CUDA (or --device cpu for the plumbing)", file=sys.stderr)
        return 1
    device_name = torch.cuda.get_device_name() if args.device == "cuda" else "the CPU"
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        warm = gpu_config("splatfacto", args, out, args.warmup_steps)
        warm.timestamp = "warmup"
        warm.logging.profile_phases = False
        trainer = Trainer(warm)
        t0 = time.perf_counter()
        run_dir = trainer.train()
        warm_s = time.perf_counter() - t0
        n_gaussians = trainer.model.num_points
        height, width = trainer.datamanager.train_dataset.image_uint8(0).shape[:2]
        print(f"warm-up: splatfacto {args.warmup_steps} steps on {device_name} -> {n_gaussians} "
              f"Gaussians at {width}x{height} in {warm_s:.1f} s ({1000 * warm_s / args.warmup_steps:.1f} ms/step "
              "incl. densification and evaluation)")
        state = {k: v.detach() for k, v in trainer.model.gauss_params.items()}
        rows: dict[str, list[dict]] = {name: [] for name in (*VARIANTS, "gsplat-simple-loop")}
        for _ in range(args.rounds):
            for name, (method, how) in VARIANTS.items():
                rows[name].append(timed_method(method, args, out, run_dir, n_gaussians, **how))
            rows["gsplat-simple-loop"].append(reference_loop(args, state, trainer.datamanager.train_dataset,
                                                             args.steps))
    median = {m: {k: statistics.median(r[k] for r in rs) for k in rs[0] if k != "sources"} for m, rs in rows.items()}
    base = median["splatfacto"]["step"]
    print(f"\nms per step on {device_name} (median of {args.rounds} rounds x {args.steps} steps; "
          f"{args.scene.name} {width}x{height}, {n_gaussians} Gaussians; phases "
          f"{'synchronised' if args.profile_phases else 'not synchronised (no per-phase split)'})\n")
    cols = list(PHASES) if args.profile_phases else []
    counts = ["syncs", "launches"] if args.count_syncs else []
    print("| method | " + " | ".join(cols + ["step", "vs splatfacto", "Gaussians"] + counts) + " |")
    print("|" + "---|" * (len(cols) + 4 + len(counts)))
    for method, values in median.items():
        cells = [f"{values[p]:.2f}" if p in values else "-" for p in cols]
        cells += [f"{values['step']:.2f}", f"{values['step'] / base:.3f}x", f"{int(values['gaussians'])}"]
        cells += [f"{values[c]:.1f}" for c in counts]
        print(f"| {method} | " + " | ".join(cells) + " |")
    if args.count_syncs:
        print_sync_sources(rows, "CUDA's sync debug mode" if args.device == "cuda" else
                           "the CPU-side detector on the torch path (benchmarks/host_syncs.py), the rasterizer's left out")
    simple = median["gsplat-simple-loop"]["step"]
    print(f"\nour splatfacto / the gsplat-style loop: {base / simple:.3f}x (target <= {LOOP_TARGET:.2f}x: "
          f"{'met' if base / simple <= LOOP_TARGET else 'NOT met'}; the loop has no density control, no schedules, no "
          "checks, one camera per step like ours)")
    ratio = median["kc-splatfacto"]["step"] / base
    print(f"\nkc-splatfacto / splatfacto step time: {ratio:.3f}x (target <= {TARGET_RATIO:.2f}x): "
          f"{'met' if ratio <= TARGET_RATIO else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
