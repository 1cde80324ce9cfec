"""Hostile but fair input to the newer tools, third round (issue 37), table-driven: each case prepares what it needs
(a tiny finished run, a tiny finished study, a tiny run trained through kc-train that a command line can resume), runs
one command in-process and checks the exit code, that a user error (exit 2) or a Ctrl-C (exit 130) is one line
without a traceback holding the expected fragment, the one-line warning a case expects, and the case's own property.

Categories (the issue's): 1 work lost (an older scene kept when its replacement fails), 2 hangs (fail within a
bounded time), 3 silent wrong results in kc-bench and kc-eval, 4 silent wrong results in kc-process-data, 5
tracebacks for user mistakes and interruptions (an output folder that is a file, a malformed
KC_SPLATFACTO_METHOD_CONFIGS, a plugin module that raises, a camera path too narrow to render, Ctrl-C in
kc-process-data's set-up and feature extraction, a resume whose metrics.jsonl cannot be appended to, a logging package
that is installed but fails to import), 6 unclear messages (a config.yml that lost a line, a method that replaces a
built-in name, the default output folder named as a flag), 7 left from the second round (a run folder without a
checkpoint), 8 what a new user sees (the demo's note as one warning line, kc-viewer's frustums sized to the cameras'
spacing). A logging backend failing mid-run (category 1) is tested in tests/engine/test_loggers.py.

Interruptions are made deterministic by raising KeyboardInterrupt from the patched step (no timed signals); a
read-only metrics.jsonl by a patched ``os.open`` that refuses to open it for writing (as root, ``chmod`` does not stop
writes), and by a folder in its place.
"""

from __future__ import annotations

import csv
import errno
import io
import json
import os
import shutil
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from kc_splatfacto.cli import bench
from kc_splatfacto.cli import eval as kc_eval
from kc_splatfacto.cli import process_data as kc_process_data
from kc_splatfacto.cli import render as kc_render
from kc_splatfacto.cli import train as kc_train
from kc_splatfacto.cli import viewer as kc_viewer
from kc_splatfacto.data import sfm
from kc_splatfacto.engine.checkpoints import CHECKPOINT_DIR, list_checkpoints
from kc_splatfacto.engine.config import load_config, save_config
from kc_splatfacto.engine.trainer import Trainer
from tests.training_utils import tiny_demo_config

OVERRIDES = ["--set", "pipeline.model.steps_scale=0.02", "pipeline.model.num_downscales=0"]
#: kc-train's flags of the resumable template run (``root/resumable``): 2 steps of splatfacto on the demo scene at SH
#: degree 1 (not the default 3, so a config.yml that lost that line no longer fits the checkpoint)
TRAIN = ["splatfacto", "--data", "demo", "--steps-per-eval-all-images", "0", "--logging.progress-bar", "False",
         "--final-lpips-nets", "--pipeline.model.num-downscales", "0", "--pipeline.model.steps-scale", "0.02",
         "--pipeline.model.sh-degree", "1"]


def study(steps: int = 6, methods: tuple[str, ...] = ("splatfacto",), seeds: tuple[str, ...] = ("0",),
          data: tuple[str, ...] = ("demo",)) -> list[str]:
    """A tiny demo study's flags (evaluations at step 3 and the last), without its output folder."""
    return ["--data", *data, "--methods", *methods, "--seeds", *seeds, "--max-num-iterations", str(steps),
            "--num-evals", "1", "--eval-at-steps", "3", *OVERRIDES]

BOUND_S = 30.0
"""a hang case must end within this many seconds"""


@dataclass
class Case:
    """``args(root)`` is the command line after the tool's name (``root``: the case's folder, holding ``run``, a
    finished run, ``study``, a finished 6-step study, and ``resumable``, a run of ``TRAIN``); ``code``/``fragment``
    what must come out; ``warning`` a fragment of the one warning line the tool must print; ``edit(root)`` changes
    files, ``patch(root, monkeypatch)`` the process (undone after the case); ``check(root)`` the case's own property
    afterwards."""

    id: str
    category: int
    tool: str
    args: Callable[[Path], list[str]]
    code: int
    fragment: str
    edit: Callable[[Path], None] = lambda root: None
    check: Callable[[Path], None] | None = None
    patch: Callable[[Path, pytest.MonkeyPatch], None] | None = None
    warning: str | None = None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _without_checkpoints(root: Path) -> None:
    shutil.rmtree(root / "run" / "nerfstudio_models")
    (root / "run" / "nerfstudio_models").mkdir()


def _without_scene(root: Path) -> None:
    config = load_config(root / "run" / "config.yml")
    config.pipeline.datamanager.dataparser.data = Path(".")
    save_config(config, root / "run" / "config.yml")


def _photos(root: Path) -> None:
    """Three photos of noise in root/photos (SfM finds no pair in them) and an older scene in root/scene."""
    import cv2
    import numpy as np

    (root / "photos").mkdir()
    for i in range(3):
        noise = np.random.default_rng(i).integers(0, 256, (60, 80, 3), dtype=np.uint8)
        assert cv2.imwrite(str(root / "photos" / f"{i}.jpg"), noise)
    (root / "scene" / "sparse" / "0").mkdir(parents=True)
    (root / "scene" / "sparse" / "0" / "cameras.txt").write_text("the older scene")


def _truncated_photo(root: Path) -> None:
    _photos(root)
    data = (root / "photos" / "2.jpg").read_bytes()
    (root / "photos" / "2.jpg").write_bytes(data[: len(data) // 2])


def _photos_in_a_subfolder(root: Path) -> None:
    _photos(root)
    (root / "photos" / "DCIM").mkdir()
    for photo in (root / "photos").glob("*.jpg"):
        photo.replace(root / "photos" / "DCIM" / photo.name)


def _older_scene_kept(root: Path) -> None:
    assert (root / "scene" / "sparse" / "0" / "cameras.txt").read_text() == "the older scene"
    assert sorted(p.name for p in root.iterdir() if p.name.startswith(".")) == []


def _plugin_that_raises(root: Path) -> None:
    (root / "kc_hostile_plugin.py").write_text("raise RuntimeError(\"the plugin's own bug\")\n")
    sys.path.insert(0, str(root))  # taken out again by the test (monkeypatch of sys.path)
    os.environ["KC_SPLATFACTO_METHOD_CONFIGS"] = "mine=kc_hostile_plugin:spec"


def _final_step_is_the_budget(step: int) -> Callable[[Path], None]:
    def check(root: Path) -> None:
        with (root / "study" / "evals.csv").open() as handle:
            rows = list(csv.DictReader(handle))
        assert max(int(r["step"]) for r in rows) == step  # the 6-step runs' later evaluation is not reported

    return check


PROCESS = ["images", "--data"]


# ------------------------------------------------------------------------------------------ category 5, 6, 8 helpers
def _narrow_camera_path(root: Path) -> None:
    """A one-camera path whose field of view (1e-300 degrees) gives an infinite focal length in float32."""
    pose = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 4, 0, 0, 0, 1]
    (root / "narrow.json").write_text(json.dumps({"camera_type": "perspective", "render_width": 64,
                                                  "render_height": 48, "camera_path": [
                                                      {"camera_to_world": pose, "fov": 1e-300, "aspect": 4 / 3}]}))


def _ctrl_c_in(name: str) -> Callable[[Path, pytest.MonkeyPatch], None]:
    """kc-process-data's step ``name`` (a function of kc_splatfacto.data.sfm) is where Ctrl-C is pressed."""

    def patch(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        def interrupted(*args, **kwargs):
            raise KeyboardInterrupt

        monkeypatch.setattr(sfm, name, interrupted)

    return patch


def _nothing_new_in(folder: str) -> Callable[[Path], None]:
    def check(root: Path) -> None:
        assert not (root / folder).exists()  # not even the parent folders --output-dir named

    return check


def _no_run_in(folder: str) -> Callable[[Path], None]:
    def check(root: Path) -> None:
        assert not list((root / folder).rglob("*"))  # refused before the run folder (--output-dir itself may exist)

    return check


def _no_output_dir(folder: str) -> Callable[[Path], None]:
    def check(root: Path) -> None:
        assert not (root / folder).exists()  # refused before any folder is made

    return check


def _older_scene_kept_after_ctrl_c(root: Path) -> None:
    _older_scene_kept(root)
    assert sorted(p.name for p in (root / "scene").iterdir()) == ["sparse"]


RESUME = ["--load-dir", "resumable/nerfstudio_models", "--max-num-iterations", "3"]


def _resume(root: Path) -> list[str]:
    return [*TRAIN, *(str(root / a) if a.startswith("resumable") else a for a in RESUME)]


def _metrics_log_is_a_folder(root: Path) -> None:
    (root / "resumable" / "metrics.jsonl").replace(root / "metrics.jsonl.kept")
    (root / "resumable" / "metrics.jsonl").mkdir()


def _metrics_log_read_only(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``os.open`` and ``io.open`` (``Path.open``'s) refuse to open the resumable run's metrics.jsonl for writing,
    as the kernel does for a read-only file when the user is not root."""
    log, real_os_open, real_io_open = str(root / "resumable" / "metrics.jsonl"), os.open, io.open

    def refused(path) -> PermissionError:
        return PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.fspath(path))

    def os_open(path, flags, *args, **kwargs):
        if os.fspath(path) == log and flags & (os.O_WRONLY | os.O_RDWR):
            raise refused(path)
        return real_os_open(path, flags, *args, **kwargs)

    def io_open(file, mode="r", *args, **kwargs):
        if isinstance(file, (str, os.PathLike)) and os.fspath(file) == log and set(mode) & set("wax+"):
            raise refused(file)
        return real_io_open(file, mode, *args, **kwargs)

    monkeypatch.setattr(os, "open", os_open)
    monkeypatch.setattr(io, "open", io_open)


def _not_resumed(root: Path) -> None:
    assert [p.name for p in list_checkpoints(root / "resumable" / CHECKPOINT_DIR)] == ["step-000000002.ckpt"]


def _resumed_to_step_3(root: Path) -> None:
    assert [p.name for p in list_checkpoints(root / "resumable" / CHECKPOINT_DIR)] == ["step-000000003.ckpt"]


def _broken_wandb(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """An installed wandb whose import raises (as a protobuf version clash does), found before the real one."""
    (root / "broken" / "wandb").mkdir(parents=True)
    (root / "broken" / "wandb" / "__init__.py").write_text(
        'raise TypeError("Descriptors cannot be created directly.\\nIf this call came from a _pb2.py file ...")\n')
    for name in [m for m in sys.modules if m == "wandb" or m.startswith("wandb.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(root / "broken"))


def _without_line(pattern: str) -> Callable[[Path], None]:
    def edit(root: Path) -> None:
        config = root / "resumable" / "config.yml"
        lines = config.read_text().splitlines(keepends=True)
        kept = [line for line in lines if not line.startswith(pattern)]
        assert len(kept) == len(lines) - 1
        config.write_text("".join(kept))

    return edit


def _in_a_folder_where_outputs_is_a_file(root: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    (root / "elsewhere").mkdir()
    (root / "elsewhere" / "outputs").write_text("a file where kc-train's default output folder would go")
    monkeypatch.chdir(root / "elsewhere")


OPENED: dict[str, object] = {}
"""the viewer the ``kc-viewer (opened)`` tool opened last, for its case's check"""


def _open_viewer(argv: list[str]) -> int:
    """What kc-viewer does up to serving (``open_viewer`` on a free port), the viewer kept for the check, stopped."""
    viewer = kc_viewer.open_viewer(Path(argv[argv.index("--load-config") + 1]), port=0)
    viewer.stop()
    OPENED["viewer"] = viewer
    return 0


def _frustums_sized_to_the_spacing(root: Path) -> None:
    """A tenth of the median distance from a training camera to its nearest neighbour, computed by brute force."""
    viewer = OPENED.pop("viewer")
    centres = np.linalg.inv(viewer.train_cameras.viewmats.double().numpy())[:, :3, 3]
    distances = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    np.fill_diagonal(distances, np.inf)
    assert viewer._frustum_scale == pytest.approx(0.1 * np.median(distances.min(axis=1)), rel=1e-9)
    assert len(viewer._frustums) == len(centres)


TOOLS = {"kc-bench": bench.entrypoint, "kc-eval": kc_eval.entrypoint, "kc-viewer": kc_viewer.entrypoint,
         "kc-process-data": kc_process_data.entrypoint, "kc-render": kc_render.entrypoint,
         "kc-train": kc_train.entrypoint, "kc-viewer (opened)": _open_viewer}

CASES = [
    # 1: work lost
    Case("process-data-overwrite-that-fails", 1, "kc-process-data", lambda root: [
        *PROCESS, str(root / "photos"), "--output-dir", str(root / "scene"), "--overwrite"], 2,
         "no initial image pair found", edit=_photos, check=_older_scene_kept),
    # 2: hangs
    Case("viewer-port-out-of-range", 2, "kc-viewer", lambda root: ["--load-config", str(root / "run" / "config.yml"),
                                                                  "--port", "70000"], 2,
         "--port must be an integer in 0..65535"),
    Case("viewer-max-render-pixels-0", 5, "kc-viewer", lambda root: ["--load-config", str(root / "run" / "config.yml"),
                                                                    "--max-render-pixels", "0"], 2,
         "--max-render-pixels must be at least 1"),
    Case("viewer-host-not-of-this-machine", 2, "kc-viewer", lambda root: [
        "--load-config", str(root / "run" / "config.yml"), "--host", "10.255.255.1"], 2, "cannot listen on host"),
    Case("bench-ray-address-where-nothing-listens", 2, "kc-bench", lambda root: [
        *study(), "--ray-address", f"127.0.0.1:{_free_port()}", "--output-dir", str(root / "other")], 2,
         "nothing answers there"),
    # 3: silent wrong results
    Case("bench-resume-with-a-shorter-budget", 3, "kc-bench", lambda root: [
        *study(steps=3), "--output-dir", str(root / "study"), "--resume"], 0, "runs.json",
         check=_final_step_is_the_budget(3)),
    Case("bench-scenes-of-one-name", 3, "kc-bench", lambda root: [
        *study(data=(str(root / "a" / "scene"), str(root / "b" / "scene"))), "--output-dir", str(root / "other")], 2,
         "scenes of one name"),
    Case("bench-seed-twice", 3, "kc-bench", lambda root: [*study(seeds=("0", "1", "0")), "--output-dir",
                                                          str(root / "other")], 2, "--seeds lists 0 more than once"),
    Case("bench-misspelt-baseline", 3, "kc-bench", lambda root: [
        *study(methods=("splatfacto", "kc-splatfacto")), "--baseline", "splatfacot", "--output-dir",
        str(root / "other")], 2, "did you mean splatfacto"),
    Case("eval-config-without-a-scene", 3, "kc-eval", lambda root: ["--load-config", str(root / "run" / "config.yml")],
         2, "names no scene", edit=_without_scene),
    # 4: silent wrong results in kc-process-data
    Case("process-data-truncated-photo", 4, "kc-process-data", lambda root: [
        *PROCESS, str(root / "photos"), "--output-dir", str(root / "new")], 2, "2.jpg does not decode completely",
         edit=_truncated_photo),
    Case("process-data-photos-in-a-subfolder", 4, "kc-process-data", lambda root: [
        *PROCESS, str(root / "photos"), "--output-dir", str(root / "new")], 2, "photos were found in subfolders",
         edit=_photos_in_a_subfolder),
    # 5: tracebacks
    Case("process-data-output-dir-is-a-file", 5, "kc-process-data", lambda root: [
        *PROCESS, str(root / "photos"), "--output-dir", str(root / "run" / "config.yml")], 2,
         "is a file, not a folder", edit=_photos),
    Case("bench-output-dir-is-a-file", 5, "kc-bench", lambda root: [*study(), "--output-dir",
                                                                    str(root / "run" / "config.yml")], 2,
         "is a file, not a folder"),
    Case("bench-output-dir-under-a-file", 5, "kc-bench", lambda root: [
        *study(), "--output-dir", str(root / "run" / "config.yml" / "report")], 2,
         "config.yml/report cannot be created:"),
    Case("bench-set-out-of-range", 5, "kc-bench", lambda root: [
        *study(), "--set", "pipeline.model.frequency.kc_weight=-1", "--output-dir", str(root / "other")], 2,
         "--set or the study's flags give the splatfacto runs a value out of range: "
         "pipeline.model.frequency.kc_weight = -1.0 is not allowed", check=_no_output_dir("other")),
    Case("method-configs-malformed", 5, "kc-bench", lambda root: [*study(), "--output-dir", str(root / "other")], 2,
         "'garbage' must have the form name=module:attribute",
         edit=lambda root: os.environ.__setitem__("KC_SPLATFACTO_METHOD_CONFIGS", "garbage")),
    Case("method-configs-plugin-that-raises", 5, "kc-bench", lambda root: [*study(), "--output-dir",
                                                                           str(root / "other")], 2,
         "importing module 'kc_hostile_plugin' for 'mine' failed: RuntimeError: the plugin's own bug",
         edit=_plugin_that_raises),
    Case("render-camera-path-too-narrow", 5, "kc-render", lambda root: [
        "--load-config", str(root / "run" / "config.yml"), "--camera-path-filename", str(root / "narrow.json"),
        "--output-dir", str(root / "renders")], 2, "camera_path[0].fov is 1e-300 degrees, too narrow to render",
         edit=_narrow_camera_path, check=_nothing_new_in("renders")),
    Case("process-data-ctrl-c-in-feature-extraction", 5, "kc-process-data", lambda root: [
        *PROCESS, str(root / "photos"), "--output-dir", str(root / "scene"), "--overwrite"], 130,
         "nothing was written to --output-dir", edit=_photos, patch=_ctrl_c_in("extract_features"),
         check=_older_scene_kept_after_ctrl_c),
    Case("process-data-ctrl-c-in-set-up", 5, "kc-process-data", lambda root: [
        *PROCESS, str(root / "photos"), "--output-dir", str(root / "new" / "scenes" / "garden")], 130,
         "nothing was written to --output-dir", edit=_photos, patch=_ctrl_c_in("check_photos"),
         check=_nothing_new_in("new")),
    Case("resume-metrics-log-is-a-folder", 5, "kc-train", _resume, 2,
         "metrics.jsonl cannot be appended to (Is a directory)", edit=_metrics_log_is_a_folder, check=_not_resumed),
    Case("resume-metrics-log-read-only", 5, "kc-train", _resume, 2,
         "metrics.jsonl cannot be appended to (Permission denied), and a resume writes its records there: make the "
         "file writable", patch=_metrics_log_read_only, check=_not_resumed),
    Case("logging-package-that-fails-to-import", 5, "kc-train", lambda root: [
        *TRAIN, "--output-dir", str(root / "other"), "--logging.wandb"], 2,
         "--logging.wandb: the wandb package is installed but fails to import (TypeError: Descriptors cannot be "
         "created directly.)", patch=_broken_wandb, check=_no_output_dir("other")),
    # 6: unclear messages
    Case("eval-config-that-lost-a-line", 6, "kc-eval", lambda root: ["--load-config", str(root / "resumable")], 2,
         "config.yml is incomplete (edited by hand, or written by an older version?): it has no line for "
         "pipeline.model.sh_degree (its default 3 was "
         "used), and so it does not fit the checkpoint", edit=_without_line("    sh_degree:"), check=_not_resumed),
    Case("resume-config-that-lost-a-line", 6, "kc-train", _resume, 2,
         "it has no line for pipeline.model.sh_degree (its default 3 was used), and so it differs from this command "
         "(pipeline.model.sh_degree 3 vs 1): put back 'sh_degree: 1' under pipeline.model",
         edit=_without_line("    sh_degree:"), check=_not_resumed),
    Case("method-configs-replaces-a-built-in", 6, "kc-train", lambda root: [
        *TRAIN, "--output-dir", str(root / "other"), "--max-num-iterations", "0"], 2,
         "--max-num-iterations must be at least 1",
         edit=lambda root: os.environ.__setitem__("KC_SPLATFACTO_METHOD_CONFIGS",
                                                  "splatfacto=method_configs.splatfacto_configs:kc_splatfacto"),
         warning="splatfacto=method_configs.splatfacto_configs:kc_splatfacto replaces the built-in method "
                 "'splatfacto' (method_configs.splatfacto_configs:splatfacto)"),
    Case("resume-where-outputs-is-a-file", 6, "kc-train", _resume, 0, "output folder",
         patch=_in_a_folder_where_outputs_is_a_file, check=_resumed_to_step_3),
    Case("new-run-where-outputs-is-a-file", 6, "kc-train", lambda root: [*TRAIN, "--max-num-iterations", "1"], 2,
         "--output-dir's default outputs is not a writable folder (it is a file): pass --output-dir",
         patch=_in_a_folder_where_outputs_is_a_file),
    # 7: left from the second round
    Case("eval-run-without-a-checkpoint", 7, "kc-eval", lambda root: ["--load-config", str(root / "run" / "config.yml")],
         2, "no checkpoint", edit=_without_checkpoints),
    Case("viewer-run-without-a-checkpoint", 7, "kc-viewer", lambda root: [
        "--load-config", str(root / "run" / "config.yml")], 2, "no checkpoint", edit=_without_checkpoints),
    # 8: what a new user sees (the fixed warm-up's note; the scene plan starts the demo at 1/2, which needs none)
    Case("demo-note-is-one-warning-line", 8, "kc-train", lambda root: [
        "kc-splatfacto", "--data", "demo", "--output-dir", str(root / "other"), "--max-num-iterations", "1",
        "--steps-per-eval-all-images", "0", "--logging.progress-bar", "False", "--pipeline.model.plan", "off",
        "--final-lpips-nets"], 0,
         "output folder", warning="FrequencyLoss: while training at 1/4 resolution (40x30 of 160x120) a db3 DWT "
                                   "supports only 2 of the 3 requested levels"),
    Case("viewer-frustums-sized-to-the-cameras-spacing", 8, "kc-viewer (opened)", lambda root: [
        "--load-config", str(root / "run" / "config.yml")], 0, "", check=_frustums_sized_to_the_spacing),
]


@pytest.fixture(scope="module")
def templates(tmp_path_factory) -> Path:
    """A finished 2-step run on the tiny demo scene, and a finished 6-step one-run study."""
    root = tmp_path_factory.mktemp("hostile-tools")
    run_dir = Trainer(tiny_demo_config("splatfacto", root / "outputs", iterations=2)).train()
    shutil.copytree(run_dir, root / "run")
    assert bench.entrypoint([*study(), "--output-dir", str(root / "study")]) == 0
    assert kc_train.entrypoint([*TRAIN, "--output-dir", str(root / "outputs"), "--timestamp", "resumable",
                                "--max-num-iterations", "2"]) == 0
    shutil.copytree(root / "outputs" / "demo" / "splatfacto" / "resumable", root / "resumable")
    shutil.rmtree(root / "outputs")
    return root


@pytest.mark.parametrize("case", CASES, ids=[f"cat{c.category}-{c.id}" for c in CASES])
def test_hostile_tool_input(case, templates, tmp_path, capsys, monkeypatch):
    root = tmp_path / "case"
    shutil.copytree(templates, root, symlinks=True)
    for name in ("a", "b"):
        (root / name / "scene").mkdir(parents=True)
    monkeypatch.setattr(sys, "path", list(sys.path))  # a case may add a folder; each case's is put back
    monkeypatch.delenv("KC_SPLATFACTO_METHOD_CONFIGS", raising=False)
    monkeypatch.setenv("KC_SPLATFACTO_METHOD_CONFIGS", "")  # registered so that monkeypatch restores it after
    case.edit(root)
    if case.patch is not None:
        case.patch(root, monkeypatch)
    monkeypatch.delenv("KC_DEBUG", raising=False)
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    start = time.monotonic()
    code = TOOLS[case.tool](case.args(root))
    elapsed = time.monotonic() - start
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    assert code == case.code, (code, captured.err[-2000:])
    warnings = [line for line in captured.err.splitlines() if line.startswith(f"{case.tool}: warning")]
    if case.warning is not None:
        assert len([line for line in warnings if case.warning in line]) == 1, captured.err
    if case.code in (2, 130):
        lines = [line for line in captured.err.splitlines()
                 if line.strip() and not line.startswith("[kc-bench]") and line not in warnings]
        start_of_line = f"{case.tool}: error: " if case.code == 2 else f"{case.tool}: interrupted (Ctrl-C): "
        assert len(lines) == 1 and lines[0].startswith(start_of_line), captured.err
        assert case.fragment in lines[0], lines[0]
    else:
        assert case.fragment in captured.out + captured.err
    if case.category == 2:
        assert elapsed < BOUND_S, f"{case.id} took {elapsed:.0f} s"
    if case.check is not None:
        case.check(root)
