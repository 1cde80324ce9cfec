"""Hostile but fair input, table-driven (issue 26): each case edits a fresh copy of a tiny scene (or run), runs one
command in-process, and checks the exit code, that a user error is one line without a traceback holding the expected
fragment, and that nothing outside the case's output folder changed (every file hashed before and after).

Categories (the issue's): 1 config values, 2 transforms.json, 3 COLMAP models, 4 images and lists, 5 runs, resumes and
outputs. Cases that must be refused stop before training; the few accepted ones train one or two steps at 48x32.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import struct
import tempfile
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

from kc_splatfacto.cli import bench as kc_bench
from kc_splatfacto.cli import eval as kc_eval
from kc_splatfacto.cli import export as kc_export
from kc_splatfacto.cli import process_data as kc_process_data
from kc_splatfacto.cli import train as kc_train
from kc_splatfacto.data import sfm
from kc_splatfacto.engine.config import load_config, save_config
from tests.hostile_scenes import colmap_scene, transforms_scene, tree_digest

TOOLS = {"kc-train": kc_train.entrypoint, "kc-eval": kc_eval.entrypoint, "kc-export": kc_export.entrypoint,
         "kc-process-data": kc_process_data.entrypoint, "kc-bench": kc_bench.entrypoint}
#: flags that make an accepted case train in seconds (no periodic eval, no VGG, few random Gaussians)
FAST = ["--max-num-iterations", "2", "--steps-per-eval-all-images", "0", "--logging.progress-bar", "False",
        "--final-lpips-nets", "--pipeline.model.num-random", "100", "--machine.device", "cpu"]


@dataclass
class Case:
    """One hostile input: ``edit(root)`` damages the copy (``root/scene``, ``root/run``), ``args(root, out)`` is the
    command line after the tool's name; ``code`` and ``fragment`` what must come out."""

    id: str
    category: int
    scene: str  # "transforms", "colmap", "colmap_bin", "spars3r", "run", "study"
    args: Callable[[Path, Path], list[str]]
    code: int
    fragment: str
    edit: Callable[[Path], None] = lambda root: None
    tool: str = "kc-train"
    patch: Callable[[pytest.MonkeyPatch], None] | None = None
    check: Callable[[Path], None] | None = None
    changes: Callable[[Path], Path] | None = None  # a folder outside ``out`` the command may write (a resumed run)
    note_lines: int | None = None  # an accepted case: the number of output lines that hold ``fragment``


def train(*extra, method="splatfacto", parser=()):
    return lambda root, out: [method, "--data", str(root / "scene"), "--output-dir", str(out), *FAST, *extra,
                              *parser]


def run_tool(*extra):
    return lambda root, out: ["--load-config", str(root / "run" / "config.yml"), *extra]


def process_data(*extra):
    return lambda root, out: ["images", "--data", str(root / "scene" / "images"), "--output-dir", str(out / "new"),
                              *extra]


#: the study of the "study" cases (``finished_study``): 3 steps of splatfacto, seed 0, on the case's COLMAP scene
#: (evaluated at steps 1 and 3: a budget of 2 finds no evaluation to reuse the run with)
STUDY_STEPS = 3


def study(*extra, steps=STUDY_STEPS):
    return lambda root, out: ["--data", str(root / "scene"), "--methods", "splatfacto", "--seeds", "0",
                              "--max-num-iterations", str(steps), "--num-evals", "1", "--output-dir",
                              str(root / "study"), "--set", "pipeline.model.num_random=100", "final_lpips_nets=",
                              *extra]


# ------------------------------------------------------------------------------------------------ scene edits


def edit_json(mutate):
    def edit(root):
        path = root / "scene" / "transforms.json"
        meta = json.loads(path.read_text())
        mutate(meta)
        path.write_text(json.dumps(meta))

    return edit


def set_frame(index, key, value):
    def mutate(meta):
        meta["frames"][index][key] = value

    return edit_json(mutate)


def set_meta(**values):
    def mutate(meta):
        for key, value in values.items():
            if value is _DELETE:
                meta.pop(key, None)
            else:
                meta[key] = value

    return edit_json(mutate)


_DELETE = object()


def frame_matrix(index, transform):
    def mutate(meta):
        matrix = np.asarray(meta["frames"][index]["transform_matrix"], np.float64)
        meta["frames"][index]["transform_matrix"] = transform(matrix)

    return edit_json(mutate)


def edit_text(relative, transform):
    def edit(root):
        path = root / relative
        path.write_text(transform(path.read_text()))

    return edit


def edit_lines(relative, transform):
    """``transform(data_lines)`` on the non-comment lines of a text file."""

    def edit(root):
        path = root / relative
        lines = path.read_text().splitlines()
        comments = [line for line in lines if line.startswith("#")]
        data = [line for line in lines if not line.startswith("#")]
        path.write_text("\n".join(comments + transform(data)) + "\n")

    return edit


def replace_field(line_index, field_index, value):
    def transform(lines):
        fields = lines[line_index].split()
        fields[field_index] = value
        lines[line_index] = " ".join(fields)
        return lines

    return transform


def truncate(relative, keep=0.6):
    def edit(root):
        path = root / relative
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * keep)])

    return edit


CAMERAS_TXT = "scene/sparse/0/cameras.txt"
IMAGES_TXT = "scene/sparse/0/images.txt"
POINTS_TXT = "scene/sparse/0/points3D.txt"


def camera_line(line):
    return edit_text(CAMERAS_TXT, lambda text: "# Camera list\n" + line + "\n")


def write_float_tiff(values):
    def edit(root):
        images = root / "scene" / "images"
        for path in sorted(images.glob("*.png")):
            image = cv2.imread(str(path)).astype(np.float32)
            path.unlink()
            cv2.imwrite(str(path.with_suffix(".tif")), values(image))
        path = root / "scene" / "transforms.json"
        path.write_text(path.read_text().replace(".png", ".tif"))

    return edit


def png_bytes(width, height):
    """A PNG header claiming ``width`` x ``height`` (data far too short): a decompression bomb's signature."""

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


def replace_image(name, data):
    def edit(root):
        (root / "scene" / "images" / name).write_bytes(data)

    return edit


def write_list(name, data):
    def edit(root):
        (root / "scene" / name).write_bytes(data)

    return edit


def edit_config(transform):
    return edit_text("run/config.yml", transform)


def scene_symlink(root):
    (root / "link").symlink_to(root / "scene", target_is_directory=True)


def disk_full_on_checkpoint(monkeypatch):
    """torch.save writes part of the file, then fails as PyTorch's zip writer does on a full disk."""
    import torch

    real = torch.save

    def full(obj, f, *args, **kwargs):
        Path(f).write_bytes(b"PK\x03\x04" + b"\0" * 100)
        raise RuntimeError("[enforce fail at inline_container.cc:626] . unexpected pos 51712 vs 51632")

    monkeypatch.setattr(torch, "save", full)
    del real


def disk_full_on_cache(monkeypatch):
    import errno

    from kc_splatfacto import atomic

    def full(path, write):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(atomic, "atomic_write", full)


#: the temp file a checkpoint write leaves when the process is killed mid-write (kill -9, power loss)
KILLED_TEMP = ".step-000000003.ckpt.k1ll3d.tmp"


def killed_mid_checkpoint(models: str):
    def edit(root):
        (root / models / KILLED_TEMP).write_bytes(b"PK\x03\x04" + b"\0" * 4096)

    return edit


def no_temp_left(models: str):
    def check(root):
        assert not (root / models / KILLED_TEMP).exists()
        assert not list((root / models).glob(".*.tmp")), list((root / models).iterdir())

    return check


STUDY_MODELS = "study/runs/scene/splatfacto/seed0/nerfstudio_models"


def run_folder_of_another_user(monkeypatch):
    """The run folder refuses this user's writes, as another user's folder does (as root, chmod stops nothing)."""
    real = tempfile.TemporaryFile

    def refuse(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).name == "run":
            raise PermissionError(13, "Permission denied", str(dir))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", refuse)


def run_folder_of_another_user_seen_by_access(monkeypatch):
    """:func:`run_folder_of_another_user`, and ``os.access`` saying so too (as it does for a user who is not root)."""
    run_folder_of_another_user(monkeypatch)
    real = os.access
    monkeypatch.setattr(os, "access", lambda path, mode, **kw: Path(path).name != "run" and real(path, mode, **kw))


def sigterm_while_matching(monkeypatch):
    """SIGTERM arrives while COLMAP matches features (extraction skipped: the case needs no SIFT features)."""

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(100):  # the handler runs between these bytecodes, as pycolmap's own checks let it
            time.sleep(0.01)
        raise AssertionError("SIGTERM did not stop kc-process-data")

    monkeypatch.setattr(sfm, "extract_features", lambda *args, **kwargs: None)
    monkeypatch.setattr(sfm, "match_features", terminated)


def only_the_old_checkpoint(root):
    models = root / "run" / "nerfstudio_models"
    assert sorted(p.name for p in models.iterdir()) == ["step-000000002.ckpt"], list(models.iterdir())


# ------------------------------------------------------------------------------------------------ the table

CASES = [
    # 1. config values: checked when the config is built, with the dotted name, the value and the range
    Case("kc-weight-nan", 1, "transforms", train("--pipeline.model.frequency.kc-weight", "nan"), 2, "pipeline.model.frequency.kc_weight"),
    Case("wavelet-weight-inf", 1, "transforms", train("--pipeline.model.frequency.wavelet-weight", "inf"), 2,
         "pipeline.model.frequency.wavelet_weight"),
    Case("cbc-weight-negative", 1, "transforms", train("--pipeline.model.frequency.cbc-weight", "-1"), 2,
         "pipeline.model.frequency.cbc_weight"),
    Case("seed-negative", 1, "transforms", train("--machine.seed", "-1"), 2, "machine.seed"),
    Case("seed-2^32", 1, "transforms", train("--machine.seed", "4294967296"), 2, "machine.seed"),
    Case("steps-per-log-0", 1, "transforms", train("--logging.steps-per-log", "0"), 2, "logging.steps_per_log"),
    Case("steps-scale-0", 1, "transforms", train("--pipeline.model.steps-scale", "0"), 2, "pipeline.model.steps_scale"),
    Case("steps-scale-nan", 1, "transforms", train("--pipeline.model.steps-scale", "nan"), 2,
         "pipeline.model.steps_scale"),
    Case("refine-every-0", 1, "transforms", train("--pipeline.model.refine-every", "0"), 2,
         "pipeline.model.refine_every"),
    Case("wavelet-levels-0-with-weight", 1, "transforms",
         train("--pipeline.model.frequency.wavelet-levels", "0", "--pipeline.model.frequency.wavelet-weight", "1e-3"), 2,
         "pipeline.model.frequency.wavelet_levels"),
    Case("ssim-lambda-2", 1, "transforms", train("--pipeline.model.ssim-lambda", "2"), 2, "pipeline.model.ssim_lambda"),
    Case("sh-degree-9", 1, "transforms", train("--pipeline.model.sh-degree", "9"), 2, "pipeline.model.sh_degree"),
    Case("sh-degree-negative", 1, "transforms", train("--pipeline.model.sh-degree", "-1"), 2,
         "pipeline.model.sh_degree"),
    Case("experiment-name-absolute", 1, "transforms", lambda root, out: train(
        "--experiment-name", str(root / "escaped"))(root, out), 2, "experiment_name"),
    Case("experiment-name-dotdot", 1, "transforms", train("--experiment-name", "../../escaped"), 2, "experiment_name"),
    Case("timestamp-dotdot", 1, "transforms", train("--timestamp", "../../../escaped"), 2, "timestamp"),
    Case("no-scene-given", 1, "transforms", lambda root, out: ["splatfacto", "--output-dir", str(out), *FAST], 2,
         "no scene given"),
    Case("lr-negative", 1, "transforms", train("--optimizers.means.optimizer.lr", "-1e-3"), 2,
         "optimizers.means.optimizer.lr"),
    Case("num-random-0", 1, "transforms", train("--pipeline.model.num-random", "0"), 2, "pipeline.model.num_random"),
    Case("cull-alpha-1.5", 1, "transforms", train("--pipeline.model.cull-alpha-thresh", "1.5"), 2,
         "pipeline.model.cull_alpha_thresh"),
    Case("eval-every-negative", 1, "transforms", train("--steps-per-eval-all-images", "-1"), 2,
         "steps_per_eval_all_images"),
    Case("eval-at-negative-step", 1, "transforms", train("--eval-at-steps", "-5"), 2, "eval_at_steps"),
    Case("bad-steps-0", 1, "transforms", train("--max-consecutive-bad-steps", "0"), 2, "max_consecutive_bad_steps"),
    Case("num-downscales-negative", 1, "transforms", train("--pipeline.model.num-downscales", "-1"), 2,
         "pipeline.model.num_downscales"),
    Case("densify-grad-negative", 1, "transforms", train("--pipeline.model.densify-grad-thresh", "-0.1"), 2,
         "pipeline.model.densify_grad_thresh"),
    Case("eval-interval-0", 1, "transforms", train(parser=("nerfstudio-data", "--eval-interval", "0")), 2,
         "eval_interval"),
    Case("split-fraction-0", 1, "transforms",
         train(parser=("nerfstudio-data", "--eval-mode", "fraction", "--train-split-fraction", "0")), 2,
         "train_split_fraction"),
    # every value checked where it enters (issue 58): the device before torch parses it, kc-process-data's flags
    # before pycolmap sees them, kc-bench's device before any run starts
    Case("device-tpu", 1, "transforms", train("--machine.device", "tpu"), 2, "--machine.device must be 'auto', 'cpu'"),
    Case("device-cuda-index", 1, "transforms", train("--machine.device", "cuda:99"), 2, "--machine.device cuda:99"),
    Case("device-uppercase", 1, "transforms", train("--machine.device", "CPU"), 2, "machine.device"),
    Case("bench-device-tpu", 1, "colmap", study("--device", "tpu"), 2, "--device 'tpu' is not a device",
         tool="kc-bench"),
    Case("bench-device-cuda-index", 1, "colmap", study("--device", "cuda:99"), 2, "--device cuda:99", tool="kc-bench"),
    Case("bench-steps-scale-not-a-number", 1, "colmap", study("--steps-scale", "abc"), 2,
         "--steps-scale must be 'none', 'auto' or a number", tool="kc-bench"),
    Case("process-data-seed-negative", 1, "transforms", process_data("--seed", "-1"), 2,
         "--seed must be an integer in 0..2147483647", tool="kc-process-data"),
    Case("process-data-seed-2^31", 1, "transforms", process_data("--seed", str(2**31)), 2, "--seed",
         tool="kc-process-data"),
    Case("process-data-max-image-size-8", 1, "transforms", process_data("--max-image-size", "8"), 2,
         "--max-image-size", tool="kc-process-data"),
    Case("process-data-num-train-0", 1, "transforms", process_data("--num-train", "0"), 2, "--num-train",
         tool="kc-process-data"),
    # 2. transforms.json against nerfstudio's format: file, frame index, field
    Case("null-frame", 2, "transforms", train(), 2, "frames[2]",
         edit=edit_json(lambda m: m["frames"].__setitem__(2, None))),
    Case("frame-is-a-list", 2, "transforms", train(), 2, "frames[1]",
         edit=edit_json(lambda m: m["frames"].__setitem__(1, [1, 2]))),
    Case("matrix-3x3", 2, "transforms", train(), 2, "frames[1].transform_matrix",
         edit=frame_matrix(1, lambda m: m[:3, :3].tolist())),
    Case("matrix-ragged", 2, "transforms", train(), 2, "frames[3].transform_matrix",
         edit=frame_matrix(3, lambda m: [m[0].tolist(), m[1, :3].tolist(), m[2].tolist(), m[3].tolist()])),
    Case("matrix-singular", 2, "transforms", train(), 2, "frames[0].transform_matrix",
         edit=frame_matrix(0, lambda m: np.concatenate([m[:, :1], m[:, :1], m[:, 2:]], axis=1).tolist())),
    Case("matrix-all-zero", 2, "transforms", train(), 2, "frames[4].transform_matrix",
         edit=frame_matrix(4, lambda m: np.zeros((4, 4)).tolist())),
    Case("matrix-scaled-rotation", 2, "transforms", train(), 2, "frames[2].transform_matrix",
         edit=frame_matrix(2, lambda m: np.concatenate([m[:3, :3] * 2.0, m[:3, 3:]], 1).tolist() + [[0, 0, 0, 1]])),
    Case("matrix-reflection", 2, "transforms", train(), 2, "frames[5].transform_matrix",
         edit=frame_matrix(5, lambda m: (m @ np.diag([-1.0, 1.0, 1.0, 1.0])).tolist())),
    Case("matrix-bottom-row", 2, "transforms", train(), 2, "frames[1].transform_matrix",
         edit=frame_matrix(1, lambda m: m[:3].tolist() + [[0, 0, 1, 1]])),
    Case("matrix-string-entry", 2, "transforms", train(), 2, "frames[0].transform_matrix",
         edit=frame_matrix(0, lambda m: [["1", *r[1:]] for r in m.tolist()])),
    Case("camera-angle-x-0", 2, "transforms", train(), 2, "camera_angle_x",
         edit=set_meta(fl_x=_DELETE, fl_y=_DELETE, cx=_DELETE, cy=_DELETE, camera_angle_x=0)),
    Case("fl-x-string", 2, "transforms", train(), 2, "fl_x", edit=set_meta(fl_x="86.2px")),
    Case("fl-x-null", 2, "transforms", train(), 2, "fl_x", edit=set_meta(fl_x=None)),
    Case("fl-x-bool", 2, "transforms", train(), 2, "fl_x", edit=set_meta(fl_x=True)),
    Case("fl-y-negative", 2, "transforms", train(), 2, "fl_y", edit=set_meta(fl_y=-40.0)),
    Case("fl-x-per-frame-nan", 2, "transforms", train(), 2, "frames[3].fl_x", edit=set_frame(3, "fl_x", float("nan"))),
    Case("w-fractional", 2, "transforms", train(), 2, "'w'", edit=set_meta(w=48.5)),
    Case("h-string", 2, "transforms", train(), 2, "'h'", edit=set_meta(h="32")),
    Case("cx-far-outside", 2, "transforms", train(), 2, "cx", edit=set_meta(cx=1000.0)),
    Case("k1-string", 2, "transforms", train(), 2, "k1", edit=set_meta(k1="0.1")),
    Case("file-path-number", 2, "transforms", train(), 2, "frames[2].file_path", edit=set_frame(2, "file_path", 17)),
    Case("applied-transform-2x2", 2, "transforms", train(), 2, "applied_transform",
         edit=set_meta(applied_transform=[[1, 0], [0, 1]])),
    Case("train-filenames-string", 2, "transforms", train(), 2, "train_filenames",
         edit=set_meta(train_filenames="images/0001.png")),
    Case("camera-model-number", 2, "transforms", train(), 2, "camera_model", edit=set_meta(camera_model=3)),
    Case("frames-empty", 2, "transforms", train(), 2, "frames", edit=set_meta(frames=[])),
    # 3. COLMAP models: the file (and line) and what is wrong, before pycolmap's C++ sees it
    Case("unsupported-camera-model", 3, "colmap", train(), 2, "SIMPLE_PINHOLE",
         edit=camera_line("1 FOV 48 32 40 40 24 16 0.1")),
    Case("unknown-camera-model-name", 3, "colmap", train(), 2, "cameras.txt:2",
         edit=camera_line("1 FANCY 48 32 40 40 24 16")),
    Case("camera-too-few-params", 3, "colmap", train(), 2, "cameras.txt:2", edit=camera_line("1 PINHOLE 48 32 40 40 24")),
    Case("camera-negative-focal", 3, "colmap", train(), 2, "cameras.txt:2",
         edit=camera_line("1 PINHOLE 48 32 -40 40 24 16")),
    Case("camera-width-0", 3, "colmap", train(), 2, "cameras.txt:2", edit=camera_line("1 PINHOLE 0 32 40 40 24 16")),
    Case("principal-point-far-outside", 3, "colmap", train(), 2, "principal point",
         edit=camera_line("1 PINHOLE 48 32 40 40 500 16")),
    Case("image-unknown-camera", 3, "colmap", train(), 2, "images.txt:4", edit=edit_lines(
        IMAGES_TXT, replace_field(2, 8, "7"))),
    Case("images-without-points-lines", 3, "colmap", train(), 2, "images.txt:3",
         edit=edit_lines(IMAGES_TXT, lambda lines: lines[0::2])),
    Case("image-line-not-a-number", 3, "colmap", train(), 2, "images.txt:2",
         edit=edit_lines(IMAGES_TXT, replace_field(0, 1, "abc"))),
    Case("image-line-no-name", 3, "colmap", train(), 2, "images.txt:6",
         edit=edit_lines(IMAGES_TXT, lambda lines: lines[:4] + [" ".join(lines[4].split()[:9])] + lines[5:])),
    Case("points-row-too-short", 3, "colmap", train(), 2, "points3D.txt:6",
         edit=edit_lines(POINTS_TXT, lambda lines: lines[:4] + ["5 0.1 0.2"] + lines[5:])),
    Case("points-colour-300", 3, "colmap", train(), 2, "points3D.txt:3",
         edit=edit_lines(POINTS_TXT, replace_field(1, 4, "300"))),
    Case("points-track-unknown-image", 3, "colmap", train(), 2, "points3D.txt:2",
         edit=edit_lines(POINTS_TXT, replace_field(0, 8, "99"))),
    Case("truncated-images-bin", 3, "colmap_bin", train(), 2, "images.bin", edit=truncate("scene/sparse/0/images.bin")),
    Case("truncated-cameras-bin", 3, "colmap_bin", train(), 2, "cameras.bin",
         edit=truncate("scene/sparse/0/cameras.bin", 0.5)),
    Case("truncated-points3d-bin", 3, "colmap_bin", train(), 2, "points3D.bin",
         edit=truncate("scene/sparse/0/points3D.bin", 0.7)),
    # 4. images and lists
    Case("float-tiff-negative", 4, "transforms", train(), 2, ".tif is a float image", edit=write_float_tiff(lambda im: im - 100.0)),
    Case("float-tiff-above-255", 4, "transforms", train(), 2, ".tif is a float image", edit=write_float_tiff(lambda im: im * 4.0)),
    Case("decompression-bomb", 4, "transforms", train(), 2, "0003.png",
         edit=replace_image("0003.png", png_bytes(30000, 30000))),
    Case("too-small-after-downscale", 4, "colmap", train(parser=("colmap", "--downscale-factor", "8")), 2,
         "downscale"),
    Case("too-small-for-num-downscales", 4, "colmap", train("--pipeline.model.num-downscales", "4"), 2,
         "num_downscales"),
    Case("list-utf16-without-bom", 4, "spars3r", train(), 2, "train_list.txt",
         edit=write_list("train_list.txt", "0001.png\n0002.png\n".encode("utf-16-le"))),
    Case("list-latin1", 4, "spars3r", train(), 2, "train_list.txt",
         edit=write_list("train_list.txt", "0001.png\ncaf\xe9.png\n".encode("latin-1"))),
    Case("list-invisible-character", 4, "spars3r", train(), 2, "\\u200b",
         edit=write_list("train_list.txt", "0001.png\n\u200b0002.png\n".encode())),
    # 5. runs, resumes, outputs
    Case("resume-other-downscale", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run"), "--max-num-iterations", "3", parser=("colmap", "--downscale-factor", "2"))(
        root, out), 2, "downscale_factor"),
    Case("resume-other-sh-degree", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run"), "--max-num-iterations", "3", "--pipeline.model.sh-degree", "1")(root, out),
        2, "pipeline.model.sh_degree"),
    Case("resume-other-ssim-lambda", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run"), "--max-num-iterations", "3", "--pipeline.model.ssim-lambda", "0.5")(root, out),
        2, "pipeline.model.ssim_lambda"),
    Case("eval-checkpoint-of-other-sh-degree", 5, "run", run_tool(), 2, "sh_degree", tool="kc-eval",
         edit=edit_config(lambda t: t.replace("sh_degree: 3", "sh_degree: 1"))),
    Case("export-checkpoint-of-other-method", 5, "run", run_tool("--output-path", "{out}/x.ply"), 2, "kc-splatfacto",
         tool="kc-export", edit=edit_config(lambda t: t.replace("method_name: splatfacto", "method_name: kc-splatfacto"))),
    Case("config-unknown-key", 5, "run", run_tool(), 2, "ssim_lamda", tool="kc-eval",
         edit=edit_config(lambda t: t.replace("  ssim_lambda: 0.2", "  ssim_lamda: 0.2"))),
    Case("config-wrong-type", 5, "run", run_tool(), 2, "max_num_iterations", tool="kc-eval",
         edit=edit_config(lambda t: t.replace("max_num_iterations: 2", "max_num_iterations: many"))),
    Case("config-wrong-type-float", 5, "run", run_tool(), 2, "ssim_lambda", tool="kc-export",
         edit=edit_config(lambda t: t.replace("ssim_lambda: 0.2", "ssim_lambda: [0.2]"))),
    Case("eval-output-is-a-folder", 5, "run", lambda root, out: run_tool("--output-path", str(out))(root, out), 2,
         "folder", tool="kc-eval"),
    Case("export-output-is-a-folder", 5, "run", lambda root, out: run_tool("--output-path", str(out))(root, out), 2,
         "folder", tool="kc-export"),
    Case("eval-scene-moved", 5, "run", run_tool(), 2, "config.yml", tool="kc-eval",
         edit=lambda root: (root / "scene").rename(root / "scene-moved")),
    Case("checkpoint-disk-full", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run"), "--max-num-iterations", "3")(root, out), 2, "disk",
         patch=disk_full_on_checkpoint, check=only_the_old_checkpoint, changes=lambda root: root / "run"),
    Case("cache-disk-full", 5, "colmap", train(parser=("colmap", "--downscale-factor", "2")), 2, "space",
         patch=disk_full_on_cache),
    # what a crash leaves, refusals before the study starts, messages that name the way out (issue 58)
    Case("bench-resume-budget-below-checkpoints", 5, "study", study("--resume", steps=2), 2,
         "--max-num-iterations 3 (or more)", tool="kc-bench"),
    Case("resume-run-folder-of-another-user", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run"), "--max-num-iterations", "3")(root, out), 2, "--load-dir COPY",
         patch=run_folder_of_another_user),
    Case("eval-method-name-misspelt", 5, "run", run_tool(), 2, "method_name 'splatfactoo' is not a registered method",
         tool="kc-eval", edit=edit_config(lambda t: t.replace("method_name: splatfacto", "method_name: splatfactoo"))),
    Case("resume-method-name-misspelt", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run"), "--max-num-iterations", "3")(root, out), 2,
         "method_name 'splatfactoo' is not a registered method",
         edit=edit_config(lambda t: t.replace("method_name: splatfacto", "method_name: splatfactoo"))),
    Case("process-data-sigterm-while-matching", 5, "transforms", process_data(), 130, "interrupted (SIGTERM)",
         tool="kc-process-data", patch=sigterm_while_matching),
    # accepted: a user passes what they naturally would
    Case("resume-removes-killed-checkpoint-temp", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run"), "--max-num-iterations", "3")(root, out), 0,
         "removed 1 unfinished checkpoint file", edit=killed_mid_checkpoint("run/nerfstudio_models"),
         check=no_temp_left("run/nerfstudio_models"), changes=lambda root: root / "run", note_lines=1),
    Case("resume-run-folder-of-another-user-in-a-new-folder", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run"), "--max-num-iterations", "3", "--resume-from-other-run", "True")(root, out), 0,
         "output folder", patch=run_folder_of_another_user_seen_by_access),
    Case("bench-resume-removes-killed-checkpoint-temp", 5, "study", study("--resume"), 0,
         "removed 1 unfinished checkpoint file", tool="kc-bench", edit=killed_mid_checkpoint(STUDY_MODELS),
         check=no_temp_left(STUDY_MODELS), changes=lambda root: root / "study", note_lines=1),
    Case("load-config-run-folder", 5, "run", lambda root, out: ["--load-config", str(root / "run"), "--output-path",
                                                               str(out / "m.json")], 0, "PSNR", tool="kc-eval"),
    Case("load-dir-ckpt-file", 5, "run", lambda root, out: train(
        "--load-dir", str(root / "run" / "nerfstudio_models" / "step-000000002.ckpt"), "--max-num-iterations", "3")(
        root, out), 0, "output folder", changes=lambda root: root / "run"),
    Case("resume-through-symlink", 5, "run", lambda root, out: [
        "splatfacto", "--data", str(root / "link"), "--output-dir", str(out), *FAST, "--load-dir", str(root / "run"),
        "--max-num-iterations", "3"], 0, "output folder", edit=scene_symlink, changes=lambda root: root / "run"),
]


def _fix_args(args: list[str], out: Path) -> list[str]:
    return [a.replace("{out}", str(out)) for a in args]


@pytest.fixture(scope="module")
def templates(tmp_path_factory):
    """The scenes, built once; a case copies the one it needs."""
    base = tmp_path_factory.mktemp("hostile-templates")
    built = {
        "transforms": transforms_scene(base / "transforms"),
        "colmap": colmap_scene(base / "colmap"),
    }
    try:  # a binary model is written by pycolmap: where it is absent (the GPU image) only its cases skip
        built["colmap_bin"] = colmap_scene(base / "colmap_bin", binary=True)
    except pytest.skip.Exception:
        pass
    spars3r = colmap_scene(base / "spars3r")
    (spars3r / "train_list.txt").write_text("0001.png\n0002.png\n0003.png\n0004.png\n0005.png\n")
    (spars3r / "test_list.txt").write_text("0000.png\n")
    built["spars3r"] = spars3r
    return built


@pytest.fixture(scope="module")
def finished_run(templates, tmp_path_factory):
    """A 2-step splatfacto run on the COLMAP scene (its own scene copy), as a template for the run cases."""
    root = tmp_path_factory.mktemp("hostile-run")
    shutil.copytree(templates["colmap"], root / "scene")
    code = kc_train.entrypoint(train("--experiment-name", "e", "--timestamp", "t", parser=("colmap",))(
        root, root / "outputs"))
    assert code == 0
    return root, root / "outputs" / "e" / "splatfacto" / "t"


@pytest.fixture(scope="module")
def finished_study(templates, tmp_path_factory):
    """A finished 3-step kc-bench study (``study()``) of splatfacto on its own copy of the COLMAP scene."""
    root = tmp_path_factory.mktemp("hostile-study")
    shutil.copytree(templates["colmap"], root / "scene")
    assert kc_bench.entrypoint(study()(root, root / "unused")) == 0
    return root


def prepare(case: Case, tmp_path: Path, templates, finished_run, request) -> Path:
    root = tmp_path / "case"
    root.mkdir()
    if case.scene == "study":  # the study and its scene, each run's config.yml pointed at the case's copy
        template = request.getfixturevalue("finished_study")
        shutil.copytree(template / "scene", root / "scene")
        shutil.copytree(template / "study", root / "study")
        for config_path in (root / "study").rglob("config.yml"):
            config = load_config(config_path)
            config.pipeline.datamanager.dataparser.data = root / "scene"
            save_config(config, config_path)
    elif case.scene == "run":
        template_root, run_dir = finished_run
        shutil.copytree(template_root / "scene", root / "scene")
        shutil.copytree(run_dir, root / "run")
        config_path = root / "run" / "config.yml"
        config = load_config(config_path)  # the copy trains on the case's copy of the scene
        config.pipeline.datamanager.dataparser.data = root / "scene"
        save_config(config, config_path)
        for old in (root / "run" / "nerfstudio_models").iterdir():
            assert old.name == "step-000000002.ckpt"
    else:
        if case.scene not in templates:
            pytest.skip(f"the {case.scene} scene could not be built here (pycolmap writes binary models)")
        shutil.copytree(templates[case.scene], root / "scene")
    return root


@pytest.mark.parametrize("case", CASES, ids=[f"cat{c.category}-{c.id}" for c in CASES])
def test_hostile_input(case, tmp_path, templates, finished_run, capsys, monkeypatch, request):
    root = prepare(case, tmp_path, templates, finished_run, request)
    case.edit(root)
    out = tmp_path / "out"
    out.mkdir()
    # a tool's default output in the current folder (kc-eval's metrics.json) lands here, not in the checkout
    monkeypatch.chdir(out)
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(out / "cache"))
    monkeypatch.delenv("KC_DEBUG", raising=False)
    for folder in [root / "scene", *(root / "scene").rglob("*")]:  # derived images go to the cache, not the scene
        if folder.is_dir() and not folder.is_symlink():
            folder.chmod(0o555)
    if case.patch is not None:
        case.patch(monkeypatch)
    allowed = case.changes(root) if case.changes is not None else None
    before = {k: v for k, v in tree_digest(tmp_path, exclude=out).items()
              if allowed is None or not k.startswith(str(allowed))}
    args = _fix_args(case.args(root, out), out)
    capsys.readouterr()  # what building a template printed is not the command's
    code = TOOLS[case.tool](args)
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    assert code == case.code, (code, captured.err[-2000:])
    if case.code in (2, 130):  # a user error, an interruption: one line
        lines = [line for line in captured.err.splitlines() if line.strip()]
        kind = "error: " if case.code == 2 else "interrupted"
        assert len(lines) == 1 and lines[0].startswith(f"{case.tool}: {kind}"), captured.err
        assert case.fragment in lines[0], lines[0]
    else:
        assert case.fragment in captured.out + captured.err
        if case.note_lines is not None:
            holding = [line for line in (captured.out + captured.err).splitlines() if case.fragment in line]
            assert len(holding) == case.note_lines, holding
    after = {k: v for k, v in tree_digest(tmp_path, exclude=out).items()
             if allowed is None or not k.startswith(str(allowed))}
    assert before == after, sorted(set(before.items()) ^ set(after.items()))[:6]
    assert not (root / "escaped").exists() and not (tmp_path / "escaped").exists()
    if case.check is not None:
        case.check(root)


def test_every_category_has_cases():
    counts = {k: sum(1 for c in CASES if c.category == k) for k in range(1, 6)}
    assert all(n >= 8 for n in counts.values()), counts
