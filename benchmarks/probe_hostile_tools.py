"""Hostile but fair use of the newer tools: one example of every category of misuse and 2-4 variants of
it, each run as its own process on the code of a checkout, each result classified as good / traceback / silent
wrong / unclear / lost work / hang.

    python benchmarks/probe_hostile_tools.py --code . --out after.json
    python benchmarks/probe_hostile_tools.py --code /path/to/an/older/checkout --out before.json
    python benchmarks/probe_hostile_tools.py --compare before.json after.json

``--code`` is put first on PYTHONPATH of every case (the interpreter is this one: its packages serve both). The
fixtures (a 2-step demo run at SH degree 1 that a command line can resume, a 1-step run on a 200-camera demo capture,
photos of noise) are trained once into ``--work``/fixtures with the code under ``--code`` and reused by later
invocations, so a before/after pair sees the same files. A case's faults are made deterministic where a test would
be timed: a Ctrl-C during set-up is a KeyboardInterrupt raised by the patched step, a read-only metrics.jsonl a
patched ``os.open``/``io.open`` (as root ``chmod`` does not stop writes); the one real SIGINT is sent when the tool
prints its feature-extraction line. What counts as good: exit 2 (130 for Ctrl-C) with one error line naming what the
case expects, no traceback, no file of the user's lost, within the case's time bound.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import textwrap
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("KC_SHARED_DATA", REPO.parent / "shared" / "data"))
CLASSES = ("good", "traceback", "silent wrong", "unclear", "lost work", "hang")
#: kc-train's flags of the resumable fixture run: 2 steps of splatfacto on the demo scene at SH degree 1
TRAIN = ["splatfacto", "--data", "demo", "--steps-per-eval-all-images", "0", "--logging.progress-bar", "False",
         "--final-lpips-nets", "--pipeline.model.num-downscales", "0", "--pipeline.model.steps-scale", "0.02",
         "--pipeline.model.sh-degree", "1"]


def study(data: tuple[str, ...] = ("demo",), methods: tuple[str, ...] = ("splatfacto",),
          seeds: tuple[str, ...] = ("0",)) -> list[str]:
    """kc-bench's flags of a 2-step study (its output folder left to the case)."""
    return ["--data", *data, "--methods", *methods, "--seeds", *seeds, "--max-num-iterations", "2", "--num-evals",
            "1", "--set", "pipeline.model.steps_scale=0.02", "pipeline.model.num_downscales=0"]


RUNNER = """\
import sys
{patch}
from kc_splatfacto.cli.{module} import entrypoint
sys.exit(entrypoint({argv!r}))
"""


@dataclass
class Result:
    rc: int | None
    out: str
    err: str
    seconds: float
    timed_out: bool


@dataclass
class Case:
    """``argv(case, fixtures)`` after the tool's name; ``judge(result, case)`` the class; ``setup(case, fixtures)``
    prepares the case's folder; ``patch`` is Python run before the tool; ``cwd`` a folder of the case to run in;
    ``interrupt_on`` a stdout fragment on which SIGINT is sent."""

    id: str
    category: int
    module: str
    argv: Callable[[Path, Path], list[str]]
    judge: Callable[[Result, Path], str]
    setup: Callable[[Path, Path], None] = lambda case, fixtures: None
    patch: str = ""
    env: dict[str, str] = field(default_factory=dict)
    cwd: str = "."
    interrupt_on: str | None = None
    timeout: float = 300.0


# ------------------------------------------------------------------------------------------------ judging
def error_lines(result: Result) -> list[str]:
    """stderr's lines that are neither warnings (``kc-x: warning...``), nor kc-bench's progress (``[kc-bench]``),
    nor blank."""
    return [line for line in result.err.splitlines()
            if line.strip() and not re.match(r"^\S+: warning", line) and not line.startswith("[")]


def refused(code: int, *fragments: str, unclear_if: tuple[str, ...] = ()) -> Callable[[Result, Path], str]:
    """Good: exit ``code`` with one error line holding every fragment (and none of ``unclear_if``)."""

    def judge(result: Result, case: Path) -> str:
        if result.timed_out:
            return "hang"
        if "Traceback" in result.err:
            return "traceback"
        if result.rc == 0:
            return "silent wrong"
        lines = error_lines(result)
        if result.rc == code and len(lines) == 1 and all(f in lines[0] for f in fragments) and not any(
                f in lines[0] for f in unclear_if):
            return "good"
        return "unclear"

    return judge


def keeps(paths: dict[str, str], then: Callable[[Result, Path], str]) -> Callable[[Result, Path], str]:
    """``lost work`` when a file of ``paths`` (relative to the case folder) no longer holds its text."""

    def judge(result: Result, case: Path) -> str:
        for name, text in paths.items():
            if not (case / name).is_file() or (case / name).read_text() != text:
                return "lost work"
        return then(result, case)

    return judge


def with_checkpoint(folder: str, then: Callable[[Result, Path], str]) -> Callable[[Result, Path], str]:
    """``lost work`` when the run stopped without a checkpoint in ``folder``."""

    def judge(result: Result, case: Path) -> str:
        if not list((case / folder).glob("nerfstudio_models/step-*.ckpt")):
            return "traceback" if "Traceback" in result.err else "lost work"
        return then(result, case)

    return judge


def warned(*fragments: str) -> Callable[[Result, Path], str]:
    """Good: one warning line holding every fragment; ``unclear`` when none says it."""

    def judge(result: Result, case: Path) -> str:
        if result.timed_out:
            return "hang"
        if "Traceback" in result.err:
            return "traceback"
        said = [line for line in result.err.splitlines() if "warning" in line and all(f in line for f in fragments)]
        return "good" if len(said) == 1 and ".py:" not in result.err else "unclear"

    return judge


def resumed_to(step: int) -> Callable[[Result, Path], str]:
    def judge(result: Result, case: Path) -> str:
        if result.timed_out:
            return "hang"
        if "Traceback" in result.err:
            return "traceback"
        if result.rc == 0 and (case / "run" / "nerfstudio_models" / f"step-{step:09d}.ckpt").is_file():
            return "good"
        lines = error_lines(result)
        return "unclear" if lines and "--output-dir outputs" in lines[0] else "silent wrong"

    return judge


def coverage_below(limit: float) -> Callable[[Result, Path], str]:
    """The viewer's training thumbnails cover at most ``limit`` of its initial view (the snippet prints COVERAGE)."""

    def judge(result: Result, case: Path) -> str:
        if "Traceback" in result.err or result.rc != 0:
            return "traceback"
        covered = float(next(line for line in result.out.splitlines() if line.startswith("COVERAGE")).split()[1])
        return "good" if covered <= limit else "unclear"

    return judge


# ------------------------------------------------------------------------------------------------ fixtures
def run_python(code: Path, source: str, cwd: Path, env: dict[str, str] | None = None, timeout: float = 600,
               interrupt_on: str | None = None) -> Result:
    environment = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", **(env or {})}
    environment["PYTHONPATH"] = os.pathsep.join(p for p in (str(code), (env or {}).get("PYTHONPATH", "")) if p)
    environment.pop("KC_DEBUG", None)
    start = time.monotonic()
    process = subprocess.Popen([sys.executable, "-c", source], cwd=cwd, env=environment, text=True,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out_lines: list[str] = []
    if interrupt_on is not None:  # read stdout until the line, then Ctrl-C
        assert process.stdout is not None
        for line in process.stdout:
            out_lines.append(line)
            if interrupt_on in line:
                process.send_signal(signal.SIGINT)
                break
    try:
        out, err = process.communicate(timeout=max(1.0, timeout - (time.monotonic() - start)))
        timed_out = False
    except subprocess.TimeoutExpired:
        process.kill()
        out, err = process.communicate()
        timed_out = True
    return Result(None if timed_out else process.returncode, "".join(out_lines) + out, err,
                  time.monotonic() - start, timed_out)


def tool(code: Path, module: str, argv: list[str], cwd: Path, **kwargs) -> Result:
    return run_python(code, RUNNER.format(patch="", module=module, argv=argv), cwd, **kwargs)


def build_fixtures(code: Path, fixtures: Path) -> None:
    """The runs and photos every case copies from (built once)."""
    if (fixtures / "done").is_file():
        return
    shutil.rmtree(fixtures, ignore_errors=True)
    fixtures.mkdir(parents=True)
    trained = tool(code, "train", [*TRAIN, "--output-dir", str(fixtures / "outputs"), "--timestamp", "run",
                                   "--max-num-iterations", "2"], fixtures)
    assert trained.rc == 0, trained.err[-3000:]
    shutil.copytree(fixtures / "outputs" / "demo" / "splatfacto" / "run", fixtures / "run")
    dense = tool(code, "train", [*TRAIN, "--output-dir", str(fixtures / "outputs"), "--timestamp", "dense",
                                 "--max-num-iterations", "1", "demo", "--num-cameras", "200", "--width", "64",
                                 "--height", "48"], fixtures)
    assert dense.rc == 0, dense.err[-3000:]
    shutil.copytree(fixtures / "outputs" / "demo" / "splatfacto" / "dense", fixtures / "dense")
    shutil.rmtree(fixtures / "outputs")
    source = textwrap.dedent(f"""\
        import cv2, numpy as np
        for i in range(3):
            noise = np.random.default_rng(i).integers(0, 256, (60, 80, 3), dtype=np.uint8)
            assert cv2.imwrite({str(fixtures / 'noise')!r} + f"/{{i}}.jpg", noise)
        """)
    (fixtures / "noise").mkdir()
    assert run_python(code, source, fixtures).rc == 0
    (fixtures / "done").write_text("")


# ------------------------------------------------------------------------------------------------ case set-ups
def copy_run(name: str = "run") -> Callable[[Path, Path], None]:
    def setup(case: Path, fixtures: Path) -> None:
        shutil.copytree(fixtures / name, case / "run")

    return setup


def noise_photos(case: Path, fixtures: Path) -> None:
    shutil.copytree(fixtures / "noise", case / "photos")


def older_scene(case: Path) -> None:
    (case / "scene" / "sparse" / "0").mkdir(parents=True)
    (case / "scene" / "sparse" / "0" / "cameras.txt").write_text("the older scene")


def then(*steps: Callable[[Path, Path], None]) -> Callable[[Path, Path], None]:
    def setup(case: Path, fixtures: Path) -> None:
        for step in steps:
            step(case, fixtures)

    return setup


def run_edit(edit: Callable[[Path], None]) -> Callable[[Path, Path], None]:
    def setup(case: Path, fixtures: Path) -> None:
        edit(case / "run")

    return setup


def drop_line(prefix: str) -> Callable[[Path], None]:
    def edit(run: Path) -> None:
        lines = (run / "config.yml").read_text().splitlines(keepends=True)
        (run / "config.yml").write_text("".join(line for line in lines if not line.startswith(prefix)))

    return edit


def without_scene(run: Path) -> None:
    text = (run / "config.yml").read_text()
    marker = "      data: !!python/object/apply:pathlib.PosixPath\n      - demo\n"
    assert marker in text
    (run / "config.yml").write_text(text.replace(marker, "      data: !!python/object/apply:pathlib.PosixPath []\n"))


def without_checkpoints(run: Path) -> None:
    shutil.rmtree(run / "nerfstudio_models")
    (run / "nerfstudio_models").mkdir()


def killed_in_first_checkpoint(run: Path) -> None:
    without_checkpoints(run)
    (run / "nerfstudio_models" / ".step-000000002.ckpt.abc123.tmp").write_bytes(b"PK\x03\x04 cut")


def metrics_log_is_a_folder(run: Path) -> None:
    (run / "metrics.jsonl").unlink()
    (run / "metrics.jsonl").mkdir()


def camera_path(fov: float) -> Callable[[Path, Path], None]:
    def setup(case: Path, fixtures: Path) -> None:
        copy_run()(case, fixtures)
        pose = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 4, 0, 0, 0, 1]
        (case / "path.json").write_text(json.dumps({"render_width": 64, "render_height": 48, "camera_path": [
            {"camera_to_world": pose, "fov": fov, "aspect": 4 / 3}]}))

    return setup


def broken_package(name: str, source: str) -> Callable[[Path, Path], None]:
    def setup(case: Path, fixtures: Path) -> None:
        (case / "broken" / name).mkdir(parents=True)
        (case / "broken" / name / "__init__.py").write_text(source)

    return setup


def file_named(name: str) -> Callable[[Path, Path], None]:
    def setup(case: Path, fixtures: Path) -> None:
        (case / name).parent.mkdir(parents=True, exist_ok=True)
        (case / name).write_text("a file where a folder would go")

    return setup


def fern_photos(case: Path, fixtures: Path) -> None:
    (case / "photos").mkdir()
    for photo in sorted((SHARED_DATA / "fern-12" / "images").iterdir()):
        shutil.copy(photo, case / "photos" / photo.name)


def truncated_png(case: Path, fixtures: Path) -> None:
    """A PNG of noise cut in half (its decoder, not its header, finds the end missing)."""
    source = "import cv2, numpy as np; cv2.imwrite('cut.png', np.random.default_rng(5).integers(0, 256, (60, 80, 3), " \
             "dtype=np.uint8))"
    subprocess.run([sys.executable, "-c", source], cwd=case / "photos", check=True)
    data = (case / "photos" / "cut.png").read_bytes()
    (case / "photos" / "cut.png").write_bytes(data[: len(data) // 2])


def plugin_that_raises(case: Path, fixtures: Path) -> None:
    (case / "plugin").mkdir()
    (case / "plugin" / "kc_probe_plugin.py").write_text('raise RuntimeError("the plugin\'s own bug")\n')


def nothing_created(folder: str, then: Callable[[Result, Path], str]) -> Callable[[Result, Path], str]:
    """``lost work`` (something half-written) when ``folder`` of the case exists afterwards."""

    def judge(result: Result, case: Path) -> str:
        verdict = then(result, case)
        return "lost work" if verdict == "good" and (case / folder).exists() else verdict

    return judge


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------------------ patches
BACKEND_FAILS = """
import kc_splatfacto.engine.loggers as loggers
calls = [0]
def write(self, record):
    calls[0] += 1
    if calls[0] == 3:
        raise RuntimeError("the backend's writer lost its folder")
loggers.TensorboardSink.write = write
"""
LOG_DISK_FULL = """
import errno, json as real_json
import kc_splatfacto.engine.metrics_log as metrics_log
class Json:
    calls = 0
    loads = staticmethod(real_json.loads)
    @staticmethod
    def dumps(*args, **kwargs):
        Json.calls += 1
        if Json.calls == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_json.dumps(*args, **kwargs)
metrics_log.json = Json
"""
READ_ONLY_LOG = """
import errno, io, os
real_os_open, real_io_open = os.open, io.open
def refused(path):
    return PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))
def is_log(path):
    return isinstance(path, (str, os.PathLike)) and os.path.abspath(os.fspath(path)).endswith("run/metrics.jsonl")
def os_open(path, flags, *args, **kwargs):
    if is_log(path) and flags & (os.O_WRONLY | os.O_RDWR):
        raise refused(path)
    return real_os_open(path, flags, *args, **kwargs)
def io_open(file, mode="r", *args, **kwargs):
    if is_log(file) and set(mode) & set("wax+"):
        raise refused(file)
    return real_io_open(file, mode, *args, **kwargs)
os.open, io.open = os_open, io_open
"""


def interrupt_in(module: str, attribute: str) -> str:
    """Python that makes ``module.attribute`` (``Class.method`` allowed) raise KeyboardInterrupt: Ctrl-C there."""
    *owners, name = attribute.split(".")
    return textwrap.dedent(f"""
        import importlib
        def pressed(*args, **kwargs):
            raise KeyboardInterrupt
        target = importlib.import_module({module!r})
        for part in {owners!r}:
            target = getattr(target, part)
        setattr(target, {name!r}, pressed)
        """)


FRUSTUM_COVERAGE = """
import sys
from pathlib import Path
import numpy as np
from kc_splatfacto.cli.viewer import open_viewer
from kc_splatfacto.engine.run_io import load_run

def coverage(view, train, scale, samples=120):
    K, W, H = view.Ks[0].double().numpy(), int(view.widths[0]), int(view.heights[0])
    c2w = np.linalg.inv(view.viewmats[0].double().numpy())
    u, v = np.meshgrid(np.linspace(0, W, samples), np.linspace(0, H, samples))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    rays = rays @ c2w[:3, :3].T
    origin, hit = c2w[:3, 3], np.zeros(len(rays), bool)
    poses = np.linalg.inv(train.viewmats.double().numpy())
    for i in range(len(train)):
        R, C, Kt = poses[i, :3, :3], poses[i, :3, 3], train.Ks[i].double().numpy()
        centre, normal = C + scale * R[:, 2], R[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = ((centre - origin) @ normal) / (rays @ normal)
        local = (origin + depth[:, None] * rays - centre) @ R
        half = scale * np.array([float(train.widths[i]) / 2 / Kt[0, 0], float(train.heights[i]) / 2 / Kt[1, 1]])
        hit |= (depth > 0) & (np.abs(local[:, :2]) <= half).all(axis=1)
    return hit.mean()

initial = load_run(CONFIG).test_dataset.cameras  # the viewer opens at the first test view
viewer = open_viewer(Path(CONFIG), port=0)
viewer.stop()
print("COVERAGE", coverage(initial, viewer.train_cameras, viewer._frustum_scale))
"""


# ------------------------------------------------------------------------------------------------ the cases
def run_config(case: Path, fixtures: Path) -> list[str]:
    return ["--load-config", str(case / "run" / "config.yml")]


def resume(case: Path, fixtures: Path) -> list[str]:
    return [*TRAIN, "--load-dir", str(case / "run" / "nerfstudio_models"), "--max-num-iterations", "3"]


PROCESS = ["images", "--data"]
CASES = [
    # 1: work lost
    Case("process-data-overwrite-whose-sfm-fails", 1, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "scene"), "--overwrite"],
         keeps({"scene/sparse/0/cameras.txt": "the older scene"}, refused(2, "no initial image pair")),
         setup=then(noise_photos, lambda c, f: older_scene(c))),
    Case("process-data-overwrite-ctrl-c-in-extraction", 1, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "scene"), "--overwrite"],
         keeps({"scene/sparse/0/cameras.txt": "the older scene"}, refused(130, "nothing was written")),
         setup=then(fern_photos, lambda c, f: older_scene(c)), interrupt_on="[1/4]"),
    Case("logging-backend-fails-mid-run", 1, "train",
         lambda c, f: [*TRAIN, "--output-dir", str(c / "out"), "--timestamp", "t", "--max-num-iterations", "6",
                       "--logging.steps-per-log", "1", "--logging.tensorboard", "True"],
         with_checkpoint("out/demo/splatfacto/t", refused(2, "failed", "resume with --load-dir")),
         patch=BACKEND_FAILS),
    Case("metrics-log-disk-full-mid-run", 1, "train",
         lambda c, f: [*TRAIN, "--output-dir", str(c / "out"), "--timestamp", "t", "--max-num-iterations", "6",
                       "--logging.steps-per-log", "1"],
         with_checkpoint("out/demo/splatfacto/t", refused(2, "metrics.jsonl", "--load-dir")), patch=LOG_DISK_FULL),
    # 2: hangs
    Case("viewer-port-70000", 2, "viewer", lambda c, f: [*run_config(c, f), "--port", "70000"],
         refused(2, "70000"), setup=copy_run(), timeout=90),
    Case("viewer-port-negative", 2, "viewer", lambda c, f: [*run_config(c, f), "--port", "-5"],
         refused(2, "-5"), setup=copy_run(), timeout=90),
    Case("viewer-host-not-of-this-machine", 2, "viewer", lambda c, f: [*run_config(c, f), "--host", "10.255.255.1"],
         refused(2, "10.255.255.1"), setup=copy_run(), timeout=90),
    Case("bench-ray-address-where-nothing-listens", 2, "bench",
         lambda c, f: [*study(), "--ray-address", f"127.0.0.1:{free_port()}", "--output-dir", str(c / "bench")],
         refused(2, "127.0.0.1"), timeout=120),
    Case("train-viewer-port-70000", 2, "train",
         lambda c, f: [*TRAIN, "--output-dir", str(c / "out"), "--viewer", "--viewer.port", "70000"],
         refused(2, "70000"), timeout=120),
    # 3: silent wrong results in kc-bench and kc-eval
    Case("eval-config-without-a-scene", 3, "eval", lambda c, f: [*run_config(c, f), "--output-path", str(c / "m.json")],
         refused(2, "scene"), setup=then(copy_run(), run_edit(without_scene))),
    Case("bench-seed-twice", 3, "bench", lambda c, f: [*study(seeds=("0", "1", "0")), "--output-dir", str(c / "bench")],
         refused(2, "--seeds")),
    Case("bench-misspelt-baseline", 3, "bench",
         lambda c, f: [*study(methods=("splatfacto", "kc-splatfacto")), "--baseline", "splatfacot",
                       "--output-dir", str(c / "bench")], refused(2, "splatfacot")),
    Case("bench-two-scenes-of-one-name", 3, "bench",
         lambda c, f: [*study(data=(str(c / "a" / "scene"), str(c / "b" / "scene"))), "--output-dir",
                       str(c / "bench")], refused(2, "scene"),
         setup=lambda c, f: [(c / d / "scene").mkdir(parents=True) for d in "ab"]),
    Case("bench-method-twice", 3, "bench", lambda c, f: [*study(methods=("splatfacto", "splatfacto")), "--output-dir",
                                                         str(c / "bench")], refused(2, "--methods")),
    Case("bench-seed-0-and-00", 3, "bench", lambda c, f: [*study(seeds=("0", "00")), "--output-dir", str(c / "bench")],
         refused(2, "--seeds")),
    # 4: silent wrong results in kc-process-data
    Case("process-data-truncated-photo", 4, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "new")], refused(2, "2.jpg"),
         setup=then(noise_photos, lambda c, f: (c / "photos" / "2.jpg").write_bytes(
             (c / "photos" / "2.jpg").read_bytes()[:400]))),
    Case("process-data-byte-identical-photos", 4, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "new")], refused(2, "0.jpg", "3.jpg"),
         setup=then(noise_photos, lambda c, f: shutil.copy(c / "photos" / "0.jpg", c / "photos" / "3.jpg"))),
    Case("process-data-photos-in-a-subfolder", 4, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "new")], refused(2, "DCIM"),
         setup=lambda c, f: shutil.copytree(f / "noise", c / "photos" / "DCIM")),
    Case("process-data-empty-photo-file", 4, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "new")], refused(2, "3.jpg"),
         setup=then(noise_photos, lambda c, f: (c / "photos" / "3.jpg").write_bytes(b""))),
    Case("process-data-truncated-png", 4, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "new")], refused(2, "cut.png"),
         setup=then(noise_photos, truncated_png)),
    # 5: tracebacks for user mistakes and interruptions
    Case("process-data-output-dir-is-a-file", 5, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "taken")], refused(2, "taken"),
         setup=then(noise_photos, file_named("taken"))),
    Case("bench-output-dir-below-a-file", 5, "bench",
         lambda c, f: [*study(), "--output-dir", str(c / "taken" / "report")], refused(2, "taken"),
         setup=file_named("taken")),
    Case("train-negative-seed", 5, "train",
         lambda c, f: [*TRAIN, "--output-dir", str(c / "out"), "--machine.seed", "-1"], refused(2, "seed")),
    Case("render-camera-path-fov-1e-300", 5, "render",
         lambda c, f: [*run_config(c, f), "--camera-path-filename", str(c / "path.json")],
         refused(2, "fov"), setup=camera_path(1e-300)),
    Case("render-camera-path-fov-5e-324", 5, "render",
         lambda c, f: [*run_config(c, f), "--camera-path-filename", str(c / "path.json")],
         refused(2, "fov"), setup=camera_path(5e-324)),
    Case("render-camera-path-fov-1e-9", 5, "render",
         lambda c, f: [*run_config(c, f), "--camera-path-filename", str(c / "path.json")],
         refused(2, "fov"), setup=camera_path(1e-9)),
    Case("render-camera-path-fov-nan", 5, "render",
         lambda c, f: [*run_config(c, f), "--camera-path-filename", str(c / "path.json")],
         refused(2, "fov"), setup=camera_path(float("nan"))),
    Case("export-run-without-a-checkpoint", 5, "export",
         lambda c, f: [*run_config(c, f), "--output-path", str(c / "s.ply")], refused(2, "checkpoint"),
         setup=then(copy_run(), run_edit(without_checkpoints))),
    Case("eval-step-that-does-not-exist", 5, "eval",
         lambda c, f: [*run_config(c, f), "--step", "999", "--output-path", str(c / "m.json")],
         refused(2, "999", "2"), setup=copy_run()),
    Case("method-configs-malformed", 5, "train", lambda c, f: [*TRAIN, "--output-dir", str(c / "out")],
         refused(2, "garbage"), env={"KC_SPLATFACTO_METHOD_CONFIGS": "garbage"}),
    Case("method-configs-plugin-that-raises", 5, "train", lambda c, f: [*TRAIN, "--output-dir", str(c / "out")],
         refused(2, "kc_probe_plugin"), setup=plugin_that_raises,
         env={"KC_SPLATFACTO_METHOD_CONFIGS": "mine=kc_probe_plugin:spec", "PYTHONPATH": "plugin"}),
    Case("logging-wandb-installed-but-broken", 5, "train",
         lambda c, f: [*TRAIN, "--output-dir", str(c / "out"), "--logging.wandb", "True"], refused(2, "wandb"),
         setup=broken_package("wandb", 'raise TypeError("Descriptors cannot be created directly.")\n'),
         env={"PYTHONPATH": "broken"}),
    Case("logging-tensorboard-installed-but-broken", 5, "train",
         lambda c, f: [*TRAIN, "--output-dir", str(c / "out"), "--logging.tensorboard", "True"],
         refused(2, "tensorboard"),
         setup=broken_package("tensorboard", 'raise AttributeError("module numpy has no attribute object")\n'),
         env={"PYTHONPATH": "broken"}),
    Case("resume-metrics-log-is-a-folder", 5, "train", resume, refused(2, "metrics.jsonl"),
         setup=then(copy_run(), run_edit(metrics_log_is_a_folder))),
    Case("resume-metrics-log-read-only", 5, "train", resume, refused(2, "metrics.jsonl"), setup=copy_run(),
         patch=READ_ONLY_LOG),
    Case("process-data-ctrl-c-in-set-up", 5, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "new" / "garden")],
         nothing_created("new", refused(130, "nothing was written")), setup=noise_photos,
         patch=interrupt_in("kc_splatfacto.data.sfm", "check_photos")),
    Case("process-data-ctrl-c-in-feature-extraction", 5, "process_data",
         lambda c, f: [*PROCESS, str(c / "photos"), "--output-dir", str(c / "new")], refused(130, "nothing was written"),
         setup=noise_photos, patch=interrupt_in("kc_splatfacto.data.sfm", "extract_features")),
    Case("eval-ctrl-c-while-loading", 5, "eval", lambda c, f: [*run_config(c, f), "--output-path", str(c / "m.json")],
         refused(130, ""), setup=copy_run(), patch=interrupt_in("kc_splatfacto.engine.pipeline", "PipelineConfig.setup")),
    Case("train-ctrl-c-in-set-up", 5, "train", lambda c, f: [*TRAIN, "--output-dir", str(c / "out")],
         refused(130, ""), patch=interrupt_in("kc_splatfacto.engine.pipeline", "PipelineConfig.setup")),
    # 6: unclear messages
    Case("eval-config-that-lost-a-line", 6, "eval", lambda c, f: [*run_config(c, f), "--output-path", str(c / "m.json")],
         refused(2, "config.yml", "sh_degree", unclear_if=("another run",)),
         setup=then(copy_run(), run_edit(drop_line("    sh_degree:")))),
    Case("export-config-that-lost-a-line", 6, "export", lambda c, f: [*run_config(c, f), "--output-path",
                                                                     str(c / "s.ply")],
         refused(2, "config.yml", "sh_degree", unclear_if=("another run",)),
         setup=then(copy_run(), run_edit(drop_line("    sh_degree:")))),
    Case("viewer-config-that-lost-a-line", 6, "viewer", run_config,
         refused(2, "config.yml", "sh_degree", unclear_if=("another run",)),
         setup=then(copy_run(), run_edit(drop_line("    sh_degree:"))), timeout=90),
    Case("resume-config-that-lost-a-line", 6, "train", resume,
         refused(2, "incomplete", "sh_degree"), setup=then(copy_run(), run_edit(drop_line("    sh_degree:")))),
    Case("method-configs-replaces-a-built-in", 6, "train",
         lambda c, f: [*TRAIN, "--output-dir", str(c / "out"), "--max-num-iterations", "0"],
         warned("splatfacto", "kc_splatfacto"),
         env={"KC_SPLATFACTO_METHOD_CONFIGS": "splatfacto=method_configs.splatfacto_configs:kc_splatfacto"}),
    Case("method-configs-names-a-method-twice", 6, "train",
         lambda c, f: ["mine", *TRAIN[1:], "--output-dir", str(c / "out"), "--max-num-iterations", "0"],
         warned("mine", "kc_splatfacto"),
         env={"KC_SPLATFACTO_METHOD_CONFIGS": "mine=method_configs.splatfacto_configs:splatfacto,"
                                              "mine=method_configs.splatfacto_configs:kc_splatfacto"}),
    Case("resume-where-outputs-is-a-file", 6, "train", resume, resumed_to(3),
         setup=then(copy_run(), file_named("elsewhere/outputs")), cwd="elsewhere"),
    Case("new-run-where-outputs-is-a-file", 6, "train", lambda c, f: [*TRAIN, "--max-num-iterations", "1"],
         refused(2, "default"), setup=file_named("elsewhere/outputs"), cwd="elsewhere"),
    Case("bench-where-bench-is-a-file", 6, "bench", lambda c, f: study(), refused(2, "default"),
         setup=file_named("elsewhere/bench"), cwd="elsewhere"),
    Case("render-where-renders-is-a-file", 6, "render", lambda c, f: [*run_config(c, f), "--no-video"],
         refused(2, "default"), setup=then(copy_run(), file_named("run/renders"))),
    # 7: left from the second round
    Case("eval-run-without-a-checkpoint", 7, "eval", lambda c, f: [*run_config(c, f), "--output-path",
                                                                   str(c / "m.json")],
         refused(2, "checkpoint"), setup=then(copy_run(), run_edit(without_checkpoints))),
    Case("viewer-run-without-a-checkpoint", 7, "viewer", run_config, refused(2, "checkpoint"),
         setup=then(copy_run(), run_edit(without_checkpoints)), timeout=90),
    Case("render-run-without-a-checkpoint", 7, "render", lambda c, f: [*run_config(c, f), "--no-video"],
         refused(2, "checkpoint"), setup=then(copy_run(), run_edit(without_checkpoints))),
    Case("resume-after-a-kill-in-the-first-checkpoint", 7, "train", resume, refused(2, "checkpoint"),
         setup=then(copy_run(), run_edit(killed_in_first_checkpoint))),
    # 8: what a new user sees
    Case("demo-note-as-one-line", 8, "train",
         lambda c, f: ["kc-splatfacto", "--data", "demo", "--output-dir", str(c / "out"), "--max-num-iterations", "1",
                       "--steps-per-eval-all-images", "0", "--logging.progress-bar", "False", "--final-lpips-nets"],
         warned("FrequencyLoss", "30x40")),
    Case("viewer-frustums-dense-capture", 8, "viewer", run_config, coverage_below(0.05), setup=copy_run("dense"),
         timeout=120),
    Case("viewer-frustums-sparse-capture", 8, "viewer", run_config, coverage_below(0.05), setup=copy_run(),
         timeout=120),
]


def case_source(case: Case, argv: list[str]) -> str:
    if case.module == "viewer" and case.judge.__qualname__.startswith("coverage_below"):
        return FRUSTUM_COVERAGE.replace("CONFIG", repr(argv[argv.index("--load-config") + 1]))
    return RUNNER.format(patch=case.patch, module=case.module, argv=argv)


def run_case(case: Case, code: Path, work: Path, fixtures: Path) -> dict:
    folder = work / "cases" / case.id
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    case.setup(folder, fixtures)
    argv = case.argv(folder, fixtures)
    env = {k: str(folder / v) if k == "PYTHONPATH" else v for k, v in case.env.items()}
    result = run_python(code, case_source(case, argv), folder / case.cwd, env, case.timeout, case.interrupt_on)
    verdict = case.judge(result, folder)
    lines = error_lines(result)
    return {"id": case.id, "category": case.category, "result": verdict, "rc": result.rc,
            "seconds": round(result.seconds, 1), "said": lines[-1][:400] if lines else "",
            "printed": result.out.strip().splitlines()[-1][:200] if result.out.strip() else "",
            "traceback_tail": result.err.strip().splitlines()[-1][:300] if "Traceback" in result.err else ""}


def compare(before_path: Path, after_path: Path) -> str:
    before, after = (json.loads(Path(p).read_text()) for p in (before_path, after_path))
    lines = ["| category | cases | before: " + " / ".join(CLASSES) + " | after: " + " / ".join(CLASSES) + " |",
             "|---|---|---|---|"]
    for category in sorted({r["category"] for r in after}):
        counts = [Counter(r["result"] for r in rows if r["category"] == category) for rows in (before, after)]
        n = sum(counts[1].values())
        lines.append(f"| {category} | {n} | " + " | ".join(" / ".join(str(c[k]) for k in CLASSES) for c in counts) + " |")
    totals = [Counter(r["result"] for r in rows) for rows in (before, after)]
    lines.append(f"| all | {len(after)} | " + " | ".join(" / ".join(str(c[k]) for k in CLASSES) for c in totals) + " |")
    changed = [f"- {a['id']}: {b['result']} -> {a['result']}" for b, a in zip(before, after) if b["result"] != a["result"]]
    return "\n".join(lines + ["", "changed:"] + changed)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--code", type=Path, default=REPO, help="the checkout whose kc_splatfacto runs the cases")
    parser.add_argument("--work", type=Path, default=Path("probe-hostile-tools"), help="fixtures and case folders")
    parser.add_argument("--out", type=Path, default=None, help="JSON of the results")
    parser.add_argument("--only", nargs="*", default=None, help="case ids to run (default: all)")
    parser.add_argument("--compare", nargs=2, type=Path, default=None, metavar=("BEFORE", "AFTER"))
    args = parser.parse_args()
    if args.compare:
        print(compare(*args.compare))
        return 0
    code, work = args.code.resolve(), args.work.resolve()
    build_fixtures(code, work / "fixtures")
    results = []
    for case in CASES:
        if args.only and case.id not in args.only:
            continue
        result = run_case(case, code, work, work / "fixtures")
        results.append(result)
        print(f"[{case.category}] {case.id}: {result['result']} ({result['seconds']} s) {result['said'][:160]}",
              flush=True)
    if args.out is not None:
        args.out.write_text(json.dumps(results, indent=1))
    counts = Counter((r["category"], r["result"]) for r in results)
    for category in sorted({r["category"] for r in results}):
        print(f"category {category}: " + ", ".join(f"{k} {counts[(category, k)]}" for k in CLASSES
                                                    if counts[(category, k)]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
