"""Density control on the CPU: our DefaultStrategy against gsplat's, per training step.

Both read the same synthetic step (one camera, every Gaussian's projected-mean gradient and per-axis radii, a quarter
of them off screen) and hold the same fields. Two timings per size: an ordinary step (statistics only: ours in one
compiled pass, gsplat's in torch ops) and a refinement step (statistics, then grow and prune with the optimizers'
state rewritten). Prints a table with gsplat's time over ours; ``--threads`` sets torch's and numba's threads.

    python benchmarks/bench_strategy.py --sizes 50000 200000 1000000 --repeats 15
"""

import kc_splatfacto  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import torch  # noqa: E402

from kc_splatfacto.cli.bench import set_threads  # noqa: E402
from kc_splatfacto.model.strategy import DefaultStrategy  # noqa: E402

WIDTH, HEIGHT = 768, 512
FIELDS = dict(prune_opa=0.1, grow_grad2d=0.0008, grow_scale3d=0.01, grow_scale2d=0.05, prune_scale3d=0.1,
              prune_scale2d=0.15, refine_scale2d_stop_iter=4000, refine_start_iter=500, refine_stop_iter=15000,
              reset_every=3000, refine_every=100, pause_refine_after_reset=112, absgrad=False)


def synthetic_step(n: int, seed: int = 0):
    """(params, optimizers, info) of one rendered camera: Gaussians, one Adam each with a step of state, and the
    rasterizer's info with the projected means' gradient (a quarter of the Gaussians unseen: radii 0)."""
    g = torch.Generator().manual_seed(seed)
    params = torch.nn.ParameterDict({
        "means": torch.randn(n, 3, generator=g), "scales": torch.randn(n, 3, generator=g) - 4.0,
        "quats": torch.randn(n, 4, generator=g), "opacities": torch.randn(n, 1, generator=g),
        "features_dc": torch.rand(n, 3, generator=g), "features_rest": torch.zeros(n, 15, 3),
    })
    optimizers = {k: torch.optim.Adam([p], lr=1e-3) for k, p in params.items()}
    for p in params.values():
        p.grad = torch.randn(p.shape, generator=g) * 1e-3
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = torch.randn(1, n, 2, generator=g) * 2e-3
    radii = torch.randint(1, 40, (1, n, 2), generator=g, dtype=torch.int32)
    radii[:, torch.rand(n, generator=g) < 0.25] = 0
    info = {"width": WIDTH, "height": HEIGHT, "n_cameras": 1, "radii": radii, "gaussian_ids": None,
            "means2d": means2d}
    return params, optimizers, info


def time_steps(strategy, n: int, step: int, repeats: int) -> float:
    """Median seconds of ``step_post_backward`` at ``step`` on a fresh synthetic step each time."""
    times = []
    for r in range(repeats):
        params, optimizers, info = synthetic_step(n, seed=r)
        state = strategy.initialize_state(scene_scale=1.0)
        strategy.step_post_backward(params, optimizers, state, 1, info)  # statistics to refine from
        start = time.perf_counter()
        strategy.step_post_backward(params, optimizers, state, step, info)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[50_000, 200_000, 1_000_000])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args()
    if args.threads:
        set_threads(args.threads)
    from gsplat.strategy import DefaultStrategy as GsplatDefaultStrategy

    ours = DefaultStrategy(**FIELDS)
    theirs = GsplatDefaultStrategy(**FIELDS)
    print(f"torch threads {torch.get_num_threads()}; {WIDTH}x{HEIGHT}, one camera, median of {args.repeats}")
    print("| Gaussians | step | ours ms | gsplat ms | gsplat / ours |")
    print("|---|---|---|---|---|")
    for n in args.sizes:
        for label, step in (("ordinary", 601), ("refinement", 600)):
            a = time_steps(ours, n, step, args.repeats)
            b = time_steps(theirs, n, step, args.repeats)
            print(f"| {n:,} | {label} | {a * 1e3:.2f} | {b * 1e3:.2f} | {b / a:.2f}x |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
