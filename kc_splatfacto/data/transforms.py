"""nerfstudio / instant-ngp ``transforms.json`` scenes.

Layout: ``<scene>/transforms.json`` (or ``--data path/to/file.json``), image paths in it relative to its folder::

    {"camera_model": "OPENCV", "fl_x", "fl_y", "cx", "cy", "w", "h", "k1", "k2", "k3", "p1", "p2",  (global/per frame)
     "frames": [{"file_path": "images/0001.png", "transform_matrix": 4x4 camera-to-world, OpenGL axes,
                 "mask_path": "masks/0001.png" (optional, white = use the pixel)}],
     "train_filenames": [...], "val_filenames": [...], "test_filenames": [...],   (optional, explicit splits)
     "ply_file_path": "sparse_pc.ply",                                            (optional seed points)
     "applied_transform": 3x4, "aabb_scale": ...}                                 (aabb_scale is ignored)

Blender-style files with only ``camera_angle_x`` (NeRF synthetic) work too: the focal length
comes from it and the image width, the principal point is the image centre, and extension-less ``file_path``s are
resolved to .png/.jpg. Frames are sorted by file name (nerfstudio). Frames whose image file is missing are listed by name in one warning
and skipped. Without split lists the split follows ``eval_mode`` like the COLMAP parser; "val" falls back to the test
list and "test" to the val list when only one is given. Distorted cameras (k1..p2) are undistorted with OpenCV and
cached; ``camera_model`` other than OPENCV/PINHOLE/SIMPLE_PINHOLE (e.g. fisheye) is an error.

The PLY points and the poses share the file's frame, so both get the normalization computed from the poses. The
reported ``dataparser_transform`` composes it with ``applied_transform`` (when present), as nerfstudio does: it
then maps the original capture's world (e.g. the COLMAP model ns-process-data converted) to the normalized world.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import torch

from kc_splatfacto.data.base import (
    DataParser,
    DataParserConfig,
    DataParserError,
    _homogeneous,
    make_cameras,
    normalize_poses,
    opencv_to_opengl,
    read_text_file,
    scene_scale_of,
)
from kc_splatfacto.data.colmap import (
    ColmapCamera,
    check_image_sizes,
    check_principal_point,
    pinhole_images,
    prepare_masks,
    split_indices,
)
from kc_splatfacto.data.images import image_size
from kc_splatfacto.data.outputs import DataparserOutputs
from kc_splatfacto.data.paths import inside_folder
from kc_splatfacto.data.ply import read_ply_points
from kc_splatfacto.registry import DataParserSpecification
from kc_splatfacto.settings import integer, real, setting

INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
DISTORTION_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's coefficient order
SUPPORTED_TRANSFORMS_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "PERSPECTIVE")


@dataclass
class TransformsDataParserConfig(DataParserConfig):
    """A nerfstudio ``transforms.json`` scene (see the module docstring)."""

    eval_mode: Literal["interval", "fraction", "filename", "all"] = "interval"
    """Split without explicit lists: "interval", "fraction", "filename" or "all" (as the COLMAP parser)."""
    eval_interval: int = setting(8, integer(1))
    """Every ``eval_interval``-th image is eval (eval_mode "interval")."""
    train_split_fraction: float = setting(0.9, real(0.0, 1.0, low_open=True))
    """Fraction of images for training (eval_mode "fraction")."""
    load_3d_points: bool = True
    """Seed points from ``ply_file_path`` when the file names one."""

    def setup(self) -> TransformsDataParser:
        return TransformsDataParser(self)


def load_transforms_json(data: Path) -> tuple[dict, Path, Path]:
    """(meta, folder the paths are relative to, json path) for a scene folder or a .json file."""
    json_path = data if data.suffix == ".json" else data / "transforms.json"
    if not json_path.is_file():
        raise DataParserError(f"{json_path} does not exist: give a folder holding transforms.json, or the .json file")
    try:
        meta = json.loads(read_text_file(json_path))
    except json.JSONDecodeError as exc:
        raise DataParserError(f"{json_path} is not valid JSON: {exc}") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise DataParserError(f"{json_path} has no 'frames' list: not a nerfstudio/instant-ngp transforms file")
    check_transforms_schema(meta, json_path)
    return meta, json_path.parent, json_path


# ------------------------------------------------------------------------------------------------ the schema

#: |R^T R - I| above this (or det R <= 0) is not a rotation: a scaled, sheared, singular or mirrored camera
ROTATION_TOLERANCE = 1e-3
NUMBER_KEYS = (*INTRINSIC_KEYS, *DISTORTION_KEYS, "camera_angle_x", "camera_angle_y")
STRING_KEYS = ("file_path", "mask_path", "camera_model", "ply_file_path", "depth_file_path")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _matrix(value, where: str, shapes: tuple[tuple[int, int], ...]) -> np.ndarray:
    """``value`` as a float64 matrix of one of ``shapes``; a :class:`DataParserError` naming ``where`` otherwise."""
    allowed = " or ".join(f"{r}x{c}" for r, c in shapes)
    if not isinstance(value, list) or not all(isinstance(row, list) for row in value):
        raise DataParserError(f"{where} must be a {allowed} list of rows of numbers, got {type(value).__name__}")
    lengths = [len(row) for row in value]
    if not all(_is_number(v) for row in value for v in row):
        bad = next(v for row in value for v in row if not _is_number(v))
        raise DataParserError(f"{where} must hold numbers only, found {bad!r}")
    if len(set(lengths)) > 1:
        raise DataParserError(f"{where} is ragged (rows of {lengths} numbers): it must be {allowed}")
    shape = (len(value), lengths[0] if lengths else 0)
    if shape not in shapes:
        raise DataParserError(f"{where} is {shape[0]}x{shape[1]}: it must be {allowed}")
    matrix = np.asarray(value, np.float64)
    if not np.isfinite(matrix).all():
        raise DataParserError(f"{where} contains NaN/inf: fix it")
    return matrix


def _check_pose(matrix: np.ndarray, where: str) -> None:
    """A camera-to-world: proper rotation (orthonormal, det +1) and, for 4x4, the bottom row 0 0 0 1."""
    if matrix.shape[0] == 4 and not np.allclose(matrix[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise DataParserError(f"{where} has the bottom row {matrix[3].tolist()}: a camera-to-world ends in 0 0 0 1")
    rotation = matrix[:3, :3]
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    det = float(np.linalg.det(rotation))
    if error > ROTATION_TOLERANCE or det <= 0:
        what = "singular" if abs(det) < 1e-9 else "a mirror (det < 0)" if det < 0 else f"not orthonormal (|R^T R - I| = {error:.3g})"
        raise DataParserError(
            f"{where}: its 3x3 rotation part is {what}, so it is not a camera pose: each transform_matrix must be a "
            "rotation and a translation (camera-to-world, OpenGL axes)"
        )


def _check_number(value, where: str) -> None:
    if not _is_number(value) or not math.isfinite(value):
        raise DataParserError(f"{where} must be a finite number, got {value!r}")


def _check_camera_values(holder: dict, where) -> None:
    """Types and ranges of the intrinsics a frame (or the file) gives; ``where(key)`` names a field in messages."""
    for key in NUMBER_KEYS:
        if key in holder:
            _check_number(holder[key], f"{where(key)}")
    for key in ("fl_x", "fl_y"):
        if key in holder and holder[key] <= 0:
            raise DataParserError(
                f"{where(key)} is {holder[key]!r}: a focal length must be > 0 (a negative one mirrors the image; "
                "flip the pose instead)"
            )
    for key in ("w", "h"):
        if key in holder and (holder[key] != int(holder[key]) or holder[key] < 1):
            raise DataParserError(f"{where(key)} is {holder[key]!r}: an image size must be a positive integer")
    for key in ("camera_angle_x", "camera_angle_y"):
        if key in holder and not 0.0 < holder[key] < math.pi:
            raise DataParserError(
                f"{where(key)} is {holder[key]!r}: a field of view in radians must be in (0, pi)"
            )
    for key in STRING_KEYS:
        if key in holder and not (isinstance(holder[key], str) and holder[key]):
            raise DataParserError(f"{where(key)} must be a non-empty string, got {holder[key]!r}")


def check_transforms_schema(meta: dict, json_path: Path) -> None:
    """``meta`` against nerfstudio's transforms.json format: types, shapes, finiteness, proper rotations, positive
    focal lengths and sizes; a :class:`DataParserError` naming the file, the frame index and the field."""
    _check_camera_values(meta, lambda key: f"{json_path}: '{key}'")
    if not meta["frames"]:
        raise DataParserError(f"{json_path}: 'frames' is empty: list at least one frame")
    for i, frame in enumerate(meta["frames"]):
        where = f"{json_path}: frames[{i}]"
        if not isinstance(frame, dict):
            raise DataParserError(
                f"{where} is {json.dumps(frame)}: every frame must be an object with 'file_path' and 'transform_matrix'"
            )
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise DataParserError(f"{where} has no '{key}': every frame needs 'file_path' and 'transform_matrix'")
        _check_camera_values(frame, lambda key, where=where: f"{where}.{key}")
        _check_pose(_matrix(frame["transform_matrix"], f"{where}.transform_matrix", ((4, 4), (3, 4))),
                    f"{where}.transform_matrix")
    if "applied_transform" in meta:
        _matrix(meta["applied_transform"], f"{json_path}: 'applied_transform'", ((3, 4), (4, 4)))
    for split in ("train", "val", "test"):
        names = meta.get(f"{split}_filenames")
        if names is not None and not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
            raise DataParserError(f"{json_path}: '{split}_filenames' must be a list of file names (strings)")


def _frame_value(frame: dict, meta: dict, key: str, json_path: Path, default=None):
    if key in frame:
        return frame[key]
    if key in meta:
        return meta[key]
    if default is not None:
        return default
    raise DataParserError(
        f"{json_path}: frame '{frame.get('file_path')}' has no '{key}' and there is no global '{key}': add it"
    )


def frame_camera(frame: dict, meta: dict, json_path: Path, image_path: Path | None = None) -> ColmapCamera:
    """The frame's camera (global values overridden per frame) as pinhole + OpenCV distortion.

    Blender-style files (NeRF synthetic) give only ``camera_angle_x``: then ``w``/``h`` come from the image header,
    ``fl_x = fl_y = w / (2 tan(camera_angle_x / 2))`` and the principal point is the image centre.
    """
    has_focal = any(key in frame or key in meta for key in ("fl_x", "fl_y"))
    if not has_focal and "camera_angle_x" in meta:
        frame = dict(frame)
        if "w" not in frame and "w" not in meta or "h" not in frame and "h" not in meta:
            frame["w"], frame["h"] = image_size(image_path) if image_path is not None else (None, None)
        width, height = (
            float(_frame_value(frame, meta, "w", json_path)),
            float(_frame_value(frame, meta, "h", json_path)),
        )
        focal = 0.5 * width / math.tan(0.5 * float(meta["camera_angle_x"]))
        frame.setdefault("fl_x", focal)
        frame.setdefault("fl_y", focal)
        frame.setdefault("cx", _frame_value(frame, meta, "cx", json_path, width / 2.0))
        frame.setdefault("cy", _frame_value(frame, meta, "cy", json_path, height / 2.0))
    values = {key: _frame_value(frame, meta, key, json_path) for key in INTRINSIC_KEYS}
    distortion = np.array([float(_frame_value(frame, meta, key, json_path, 0.0)) for key in DISTORTION_KEYS])
    camera = ColmapCamera(
        model=str(_frame_value(frame, meta, "camera_model", json_path, "OPENCV")),
        width=int(values["w"]),
        height=int(values["h"]),
        fx=float(values["fl_x"]),
        fy=float(values["fl_y"]),
        cx=float(values["cx"]),
        cy=float(values["cy"]),
        distortion=distortion,
    )
    if camera.model not in SUPPORTED_TRANSFORMS_MODELS:
        raise DataParserError(
            f"{json_path}: camera_model '{camera.model}' (frame '{frame.get('file_path')}') is not supported: use one "
            f"of {', '.join(SUPPORTED_TRANSFORMS_MODELS)} (undistort fisheye images first)"
        )
    if not np.isfinite([camera.fx, camera.fy, camera.cx, camera.cy, *distortion]).all() or camera.fx <= 0:
        raise DataParserError(f"{json_path}: frame '{frame.get('file_path')}' has invalid intrinsics")
    check_principal_point(camera, f"{json_path} (frame '{frame.get('file_path')}')")
    return camera


class TransformsDataParser(DataParser):
    config: TransformsDataParserConfig
    scene_name = "scene"
    scene_may_be_file = True  # a .json file, or the folder holding transforms.json

    def _generate_dataparser_outputs(self, split: str) -> DataparserOutputs:
        data = Path(self.config.data)
        meta, base, json_path = self.memo("transforms.json", load_transforms_json, data)

        frames: list[tuple[Path, dict]] = []
        missing: list[tuple[Path, dict]] = []
        for frame in meta["frames"]:
            if "file_path" not in frame or "transform_matrix" not in frame:
                raise DataParserError(f"{json_path}: every frame needs 'file_path' and 'transform_matrix'")
            path = inside_folder(base, frame["file_path"], f"{json_path} file_path", self.config.allow_symlinks_out)
            if not path.is_file() and path.suffix == "":  # instant-ngp's Blender exports omit the extension
                path = next(
                    (path.with_suffix(s) for s in (".png", ".jpg", ".jpeg") if path.with_suffix(s).is_file()), path
                )
                if path.suffix:  # the file actually read must stay inside too
                    named = str(Path(frame["file_path"]).with_suffix(path.suffix))
                    inside_folder(base, named, f"{json_path} file_path", self.config.allow_symlinks_out)
            (frames if path.is_file() else missing).append((path, frame))
        if missing:
            warnings.warn(
                f"{json_path}: {len(missing)} frame(s) skipped because their image file is missing: "
                + ", ".join(str(f["file_path"]) for _, f in missing), stacklevel=2
            )
        if not frames:
            raise DataParserError(f"{json_path}: none of the frames' image files exist under {base}")
        frames.sort(key=lambda item: str(item[0]))
        paths = [path for path, _ in frames]
        twice = sorted({str(p) for p, q in zip(paths, paths[1:]) if p == q})
        if twice:  # one image with two poses would be trained on twice, with contradicting cameras
            raise DataParserError(f"{json_path}: frames {', '.join(twice)} appear more than once: keep one frame each")
        # 3x4 and 4x4 may mix (the schema checked each): all made 4x4
        c2w_gl = np.stack([_homogeneous(np.asarray(frame["transform_matrix"], np.float64)[None])[0]
                           for _, frame in frames])
        bad = [str(frames[i][1]["file_path"]) for i in range(len(frames)) if not np.isfinite(c2w_gl[i]).all()]
        if bad:
            raise DataParserError(
                f"{json_path}: transform_matrix of {', '.join(bad)} contains NaN/inf: fix those frames"
            )
        c2w_cv = opencv_to_opengl(c2w_gl)

        split_lists = {s: meta.get(f"{s}_filenames") for s in ("train", "val", "test")}
        if any(v is not None for v in split_lists.values()):
            index_of = {path.resolve(): i for i, path in enumerate(paths)}

            def listed(names: list[str] | None, which: str) -> list[int]:
                if names is None:
                    return []
                idx = []
                for name in names:
                    resolved = (base / name).resolve()
                    if resolved not in index_of:
                        raise DataParserError(
                            f"{json_path}: '{name}' in {which}_filenames is not a frame with an existing image: "
                            "fix the list or add the image"
                        )
                    if index_of[resolved] in idx:
                        raise DataParserError(
                            f"{json_path}: '{name}' is listed twice in {which}_filenames: remove the duplicate"
                        )
                    idx.append(index_of[resolved])
                return idx

            train = listed(split_lists["train"], "train")
            val = listed(split_lists["val"], "val")
            test = listed(split_lists["test"], "test")
            chosen = {"train": train, "val": val or test, "test": test or val}[split]
            normalize_idx = sorted(set(train) | set(val) | set(test))
        else:
            names = [str(frame["file_path"]) for _, frame in frames]
            train, evals = split_indices(
                names, self.config.eval_mode, self.config.eval_interval, self.config.train_split_fraction
            )
            chosen = train if split == "train" else evals
            normalize_idx = list(range(len(paths)))
        if not chosen:
            raise DataParserError(f"split '{split}' of {json_path} is empty: check its split lists / eval_mode")

        normalization = normalize_poses(
            c2w_cv[normalize_idx],
            self.config.orientation_method,
            self.config.center_method,
            self.config.auto_scale_poses,
        )
        c2w_all = normalization.apply_to_c2w(c2w_cv)
        cameras = [frame_camera(frames[i][1], meta, json_path, paths[i]) for i in chosen]
        split_paths = [paths[i] for i in chosen]
        check_image_sizes(split_paths, cameras, [f"camera in {json_path.name}"] * len(chosen))
        metadata: dict = {"format": "nerfstudio-data", "skipped_frames": [str(f["file_path"]) for _, f in missing]}
        with_masks = ["mask_path" in frames[i][1] for i in chosen]
        mask_paths = None
        if any(with_masks):
            if not all(with_masks):
                raise DataParserError(
                    f"{json_path}: some frames of split '{split}' have a mask_path and others do not: give every "
                    "frame a mask or none"
                )
            mask_paths = [
                inside_folder(base, frames[i][1]["mask_path"], f"{json_path} mask_path", self.config.allow_symlinks_out)
                for i in chosen
            ]
            mask_paths = prepare_masks(self.config, mask_paths, cameras, [p.parent for p in mask_paths], metadata)
        split_paths, intrinsics, sizes = pinhole_images(
            self.config, split_paths, cameras, [p.parent for p in split_paths], metadata
        )

        transform = normalization.transform
        if "applied_transform" in meta:
            applied = np.asarray(meta["applied_transform"], np.float64)
            applied4 = np.concatenate([applied[:3, :4], [[0.0, 0.0, 0.0, 1.0]]], axis=0)
            transform = transform @ applied4
        outputs = DataparserOutputs(
            image_filenames=split_paths,
            mask_filenames=mask_paths,
            cameras=make_cameras(c2w_all[chosen], intrinsics, sizes[:, 0], sizes[:, 1]),
            split=split,
            scene_scale=scene_scale_of(c2w_all[normalize_idx]),
            dataparser_transform=torch.from_numpy(transform.astype(np.float32)),
            dataparser_scale=float(normalization.scale),
            metadata={"normalization": normalization, "json_path": json_path, **metadata},
        )
        if self.config.load_3d_points and "ply_file_path" in meta:
            ply = inside_folder(base, meta["ply_file_path"], f"{json_path} ply_file_path", self.config.allow_symlinks_out)
            try:
                xyz, rgb = read_ply_points(ply)
            except FileNotFoundError as exc:
                raise DataParserError(
                    f"ply_file_path {ply} does not exist: fix the path in transforms.json or remove it"
                ) from exc
            except ValueError as exc:
                raise DataParserError(f"could not read the point cloud {ply}: {exc}") from exc
            outputs.points3d_xyz = torch.from_numpy(normalization.apply_to_points(xyz).astype(np.float32))
            outputs.points3d_rgb = torch.from_numpy(rgb.copy())
        return outputs


def _spec():
    return DataParserSpecification(
        config=TransformsDataParserConfig(),
        description="nerfstudio / instant-ngp transforms.json (OpenGL camera-to-world, optional split lists and PLY)",
    )


nerfstudio_dataparser = _spec()
