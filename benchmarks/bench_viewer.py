"""Training speed with the live viewer attached and a browser watching, against the same run without a viewer.

The runs are identical training (a viewer never changes the numerics), so the same steps do the same work; rounds
alternate (plain, viewer, plain, viewer, ...) and the medians of the steps-per-second of the training loop (wall
clock, viewer renders included: they happen between steps) are compared. The browser is Debian's headless chromium
(software WebGL), on this same machine; with ``--orbit`` (the default) the server moves the browser's camera every
0.1 s, the worst case of a user dragging the view all along. Target: at most 1.10x the time of the plain run.

    .venv/bin/python benchmarks/bench_viewer.py [--rounds 2] [--steps 300] [--downscale 4] [--no-orbit]
"""

import os

import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import copy  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import threading  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
TARGET_RATIO = 1.10


def browser():
    """The tests' niced headless chromium (tests/viewer/browser.py), or None with the reason printed."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.viewer.browser import launch_headless_chromium

    try:
        return launch_headless_chromium()
    except RuntimeError as exc:
        print(f"bench_viewer: {exc}; skipped")
        return None


def make_config(scene: Path, out: Path, downscale: int, steps: int):
    from kc_splatfacto.registry import discover_methods

    config = copy.deepcopy(discover_methods()["splatfacto"].config)
    config.pipeline.datamanager.set_scene(scene)
    config.pipeline.datamanager.dataparser.downscale_factor = downscale
    config.output_dir = out
    config.experiment_name = "bench-viewer"
    config.max_num_iterations = steps
    config.steps_per_eval_all_images = 0
    config.steps_per_save = 10**9
    config.logging.progress_bar = False
    config.machine.device = "cpu"
    config.machine.seed = 0
    config.viewer.port = 0
    return config


def orbit(viewer, stop: threading.Event) -> None:
    """Move every browser's camera a little every 0.1 s (what dragging the view does)."""
    import numpy as np

    angle = 0.0
    while not stop.is_set():
        angle += 0.02
        for client in viewer.server.get_clients().values():
            try:
                client.camera.position = client.camera.position + 0.01 * np.array([math.cos(angle), math.sin(angle), 0])
            except AssertionError:  # no camera reported yet
                pass
        stop.wait(0.1)


def timed_run(config, driver, with_viewer: bool, move: bool) -> tuple[float, dict]:
    """(steps per second of the training loop, the viewer's counters)."""
    from kc_splatfacto.cli.train import attach_viewer

    trainer = config.setup()
    trainer.setup()
    viewer, stop, info = None, threading.Event(), {}
    if with_viewer:
        viewer = attach_viewer(trainer)
        driver.get(viewer.url)
        deadline = time.time() + 120
        while viewer.frames_sent == 0 and time.time() < deadline:
            viewer.render_pending()
            time.sleep(0.2)
        viewer.frames_sent, viewer.render_s = 0, 0.0
        if move:
            threading.Thread(target=orbit, args=(viewer, stop), daemon=True).start()
    start = time.perf_counter()
    trainer.train()
    wall = time.perf_counter() - start
    stop.set()
    if viewer is not None:
        info = {"frames": viewer.frames_sent, "render_s": viewer.render_s, "wall_s": wall}
        driver.get("about:blank")
        viewer.stop()
    return config.max_num_iterations / wall, info


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=SHARED_DATA / "castle-P30")
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--no-orbit", action="store_true", help="the browser's camera stands still")
    args = parser.parse_args()
    if not args.scene.is_dir():
        print(f"bench_viewer: scene {args.scene} not found (set KC_SHARED_DATA); skipped")
        return 0
    try:
        import viser  # noqa: F401
    except ImportError:
        print("bench_viewer: viser is not installed (pip install 'kc-splatfacto[viewer]'); skipped")
        return 0
    driver = browser()
    if driver is None:
        return 0
    rates = {"plain": [], "viewer": []}
    infos = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for round_index in range(args.rounds + 1):  # round 0 compiles the kernels and is not counted
                for mode in ("plain", "viewer"):
                    config = make_config(args.scene, Path(tmp) / f"{mode}{round_index}", args.downscale, args.steps)
                    rate, info = timed_run(config, driver, mode == "viewer", not args.no_orbit)
                    if round_index > 0:
                        rates[mode].append(rate)
                        infos.append(info) if info else None
                    print(f"round {round_index} {mode:6s}: {rate:.2f} steps/s {info}", flush=True)
    finally:
        driver.quit()
    plain, watched = statistics.median(rates["plain"]), statistics.median(rates["viewer"])
    ratio = plain / watched
    share = statistics.median(i["render_s"] / i["wall_s"] for i in infos)
    print(f"\nsplatfacto, {args.steps} steps, 1/{args.downscale} resolution, browser {'orbiting' if not args.no_orbit else 'still'}")
    print("| run | steps/s (median) | time ratio |\n| --- | --- | --- |")
    print(f"| no viewer | {plain:.2f} | 1.00 |")
    print(f"| viewer + chromium | {watched:.2f} | {ratio:.3f} |")
    print(f"viewer renders: {share:.1%} of the wall clock, {statistics.median(i['frames'] for i in infos)} frames a run")
    print(f"target: time ratio <= {TARGET_RATIO:.2f}: {'met' if ratio <= TARGET_RATIO else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
