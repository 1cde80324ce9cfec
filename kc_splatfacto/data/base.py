"""Dataparser base classes, nerfstudio's pose normalization, and the dataparser transform file.

Pose normalization follows nerfstudio's defaults exactly (``auto_orient_and_center_poses`` with orientation "up" and
centre "poses", then ``auto_scale_poses``): the mean camera "up" vector (OpenGL +y of camera-to-world) is rotated onto
+z with the minimal rotation, the mean camera centre goes to the origin, and everything is scaled so that the largest
absolute camera coordinate is 1. It is computed on train and eval poses together (nerfstudio computes it on every frame
before splitting) so that both splits live in the same world. Seed points get the same transform.

The pair (``transform`` [3,4], ``scale``) maps an original world point ``p`` to ``scale * (transform @ [p, 1])``:
nerfstudio's ``dataparser_transforms.json`` format, written by :func:`write_dataparser_transforms`.
"""

from __future__ import annotations

import json
import math
import os
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

import numpy as np
import torch

from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.data.outputs import Cameras, DataparserOutputs
from kc_splatfacto.errors import UserError
from kc_splatfacto.settings import integer, setting

SPLITS = ("train", "val", "test")
ORIENTATION_METHODS = ("up", "none")
CENTER_METHODS = ("poses", "none")
# nerfstudio's ``rotation_matrix_between`` treats vectors as parallel below this cross-product size.
PARALLEL_EPS = 1e-6
CACHE_ENV = "KC_SPLATFACTO_CACHE"
READ_ONLY_DATA_ENV = "KC_SPLATFACTO_READ_ONLY_DATA"
"""folders (separated by ``os.pathsep``) whose scenes are read-only in intent whatever their mode bits say: derived
images of a scene under one go to the cache, never into the scene (a team's shared data folder; the test suite sets
it to ``../shared/data`` for itself and every command it starts)"""


class DataParserError(UserError, ValueError):
    """Bad scene input: the message names the file or argument and what to do about it."""


def default_cache_dir() -> Path:
    """``$KC_SPLATFACTO_CACHE`` or ``~/.cache/kc_splatfacto``: generated scenes and derived (downscaled) images."""
    env = os.environ.get(CACHE_ENV)
    return Path(env).expanduser() if env else Path.home() / ".cache" / "kc_splatfacto"


@dataclass
class DataParserConfig:
    """Fields every dataparser config has; subclasses add their own and implement ``setup()``.

    Configs are plain dataclasses (saved to YAML with the run config and rebuilt from it).
    """

    data: Path = Path(".")
    """Scene folder (or file, for formats that allow it)."""
    downscale_factor: int = setting(1, integer(1))
    """Integer image downscale; resized copies are cached in ``images_N/`` (see ``cache_dir``)."""
    orientation_method: Literal["up", "none"] = "up"
    """nerfstudio's orientation: "up" (mean camera up -> +z) or "none"."""
    center_method: Literal["poses", "none"] = "poses"
    """nerfstudio's centring: "poses" (mean camera centre -> origin) or "none"."""
    auto_scale_poses: bool = True
    """Scale so the largest absolute camera coordinate is 1 (nerfstudio's ``auto_scale_poses``)."""
    allow_symlinks_out: bool = False
    """Read image files whose symlinks lead outside the scene folder (names with '..' or absolute names are refused
    whatever this says)."""
    cache_dir: Path | None = None
    """Where derived images (downscaled, undistorted) go. None: next to the scene's images when that folder is
    writable, else under ``$KC_SPLATFACTO_CACHE`` (``~/.cache/kc_splatfacto``)."""

    def setup(self) -> DataParser:
        raise NotImplementedError(f"{type(self).__name__} must implement setup()")


class DataParser:
    """Turns a scene folder into one :class:`DataparserOutputs` per split.

    A subclass implements ``_generate_dataparser_outputs(split)``. :meth:`get_dataparser_outputs` calls it once the
    split's name and the scene (:meth:`check_scene`: ``config.data`` is a folder, or a file too where
    ``scene_may_be_file``) are checked, and refuses an empty result.
    """

    config: DataParserConfig
    #: what ``config.data`` holds, as the scene check's messages name it ("COLMAP scene folder")
    scene_name: ClassVar[str] = "scene folder"
    #: whether ``config.data`` may also be a file (a transforms.json) rather than a folder only
    scene_may_be_file: ClassVar[bool] = False

    def __init__(self, config: DataParserConfig):
        self.config = config
        _check_common_config(config)

    def memo(self, key: Any, build: Any, *args: Any) -> Any:
        """``build(*args)``, computed once per parser and ``key``: the splits of one scene share one parse of its
        model (read once, whichever split is asked for first)."""
        cache = self.__dict__.setdefault("_memo", {})
        if key not in cache:
            cache[key] = build(*args)
        return cache[key]

    def get_dataparser_outputs(self, split: str = "train") -> DataparserOutputs:
        """The split's images and cameras ("train", "val" or "test"), in the normalized world."""
        if split not in SPLITS:
            raise DataParserError(f"unknown split '{split}': use one of {', '.join(SPLITS)}")
        self.check_scene()
        outputs = self._generate_dataparser_outputs(split)
        if len(outputs.image_filenames) == 0:
            raise empty_split_error(self.config, split)
        return outputs

    def check_scene(self) -> None:
        """``config.data`` is there: a folder (or, where ``scene_may_be_file``, a file); a
        :class:`DataParserError` naming it as ``scene_name`` says otherwise."""
        data = Path(self.config.data)
        if not (self.scene_may_be_file and data.exists()):
            existing_folder(data, self.scene_name, "check --data")

    def _generate_dataparser_outputs(self, split: str) -> DataparserOutputs:
        raise NotImplementedError


def existing_folder(path: Path, name: str, fix: str) -> Path:
    """``path`` when it is a folder; else a :class:`DataParserError` "``name`` ``path`` does not exist: ``fix``" (or
    "is not a folder" when something else is there)."""
    if path.is_dir():
        return path
    state = "is not a folder" if path.exists() else "does not exist"
    raise DataParserError(f"{name} {path} {state}: {fix}")


def empty_split_error(config: DataParserConfig, split: str) -> DataParserError:
    """The error for a split without images: the split, the scene and the config whose lists / eval mode chose it."""
    return DataParserError(
        f"split '{split}' of {config.data} is empty: check the split lists / eval mode of {type(config).__name__}"
    )


def _check_common_config(config: DataParserConfig) -> None:
    factor = config.downscale_factor
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise DataParserError(f"downscale_factor must be an integer >= 1, got {factor!r}")
    if config.orientation_method not in ORIENTATION_METHODS:
        raise DataParserError(
            f"orientation_method '{config.orientation_method}' is not supported: use one of {ORIENTATION_METHODS}"
        )
    if config.center_method not in CENTER_METHODS:
        raise DataParserError(f"center_method '{config.center_method}' is not supported: use one of {CENTER_METHODS}")


# ----------------------------------------------------------------------------------------------------------------
# Pose normalization (nerfstudio's camera_utils, in float64 numpy)
# ----------------------------------------------------------------------------------------------------------------


def rotation_matrix_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """[3,3] rotation taking direction ``a`` [3] onto ``b`` [3] (nerfstudio's ``rotation_matrix_between``)."""
    a = np.asarray(a, np.float64) / np.linalg.norm(a)
    b = np.asarray(b, np.float64) / np.linalg.norm(b)
    axis = np.cross(a, b)
    if np.abs(axis).sum() < PARALLEL_EPS:
        helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < PARALLEL_EPS else np.array([0.0, 1.0, 0.0])
        axis = np.cross(a, helper)
    axis = axis / np.linalg.norm(axis)
    skew = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    theta = math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0)))
    return np.eye(3) + math.sin(theta) * skew + (1.0 - math.cos(theta)) * (skew @ skew)


def auto_orient_and_center_poses(
    c2w_opengl: np.ndarray, method: str = "up", center_method: str = "poses"
) -> tuple[np.ndarray, np.ndarray]:
    """nerfstudio's ``auto_orient_and_center_poses`` for methods "up"/"none" and centres "poses"/"none".

    Args:
        c2w_opengl: [N, 3|4, 4] camera-to-world, OpenGL camera axes (x right, y up, z backward).
    Returns:
        (oriented [N, 3, 4], transform [3, 4]) with ``oriented = transform @ c2w``.
    """
    poses = np.asarray(c2w_opengl, np.float64)
    origins = poses[:, :3, 3]
    translation = origins.mean(axis=0) if center_method == "poses" else np.zeros(3)
    if center_method not in CENTER_METHODS:
        raise DataParserError(f"center_method '{center_method}' is not supported: use one of {CENTER_METHODS}")
    if method == "up":
        up = poses[:, :3, 1].mean(axis=0)
        up = up / np.linalg.norm(up)
        rotation = rotation_matrix_between(up, np.array([0.0, 0.0, 1.0]))
    elif method == "none":
        rotation = np.eye(3)
    else:
        raise DataParserError(f"orientation_method '{method}' is not supported: use one of {ORIENTATION_METHODS}")
    transform = np.concatenate([rotation, rotation @ -translation[:, None]], axis=1)
    oriented = transform @ _homogeneous(poses)
    return oriented, transform


def _homogeneous(poses: np.ndarray) -> np.ndarray:
    """[N,3|4,4] -> [N,4,4]."""
    if poses.shape[-2] == 4:
        return poses
    bottom = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), poses.shape[:-2] + (1, 4))
    return np.concatenate([poses, bottom], axis=-2)


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """Flip camera y and z axes: OpenCV (x right, y down, z forward) <-> OpenGL (x right, y up, z backward).

    Args:
        c2w: [N, 3|4, 4] camera-to-world. The flip is its own inverse, so this also maps OpenGL to OpenCV.
    """
    out = np.array(c2w, np.float64, copy=True)
    out[..., :3, 1:3] *= -1.0
    return out


# nerfstudio's COLMAP parser (``assume_colmap_world_coordinate_convention=True``, its default) first maps COLMAP's
# gravity guess (-y) to +z: world (x, y, z) -> (x, z, -y). The "up" orientation's shortest-arc rotation depends on
# this starting frame (it fixes the azimuth), so COLMAP-based parsers apply it too, to land in nerfstudio's world.
COLMAP_APPLIED_TRANSFORM = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0]])


@dataclass
class PoseNormalization:
    """The normalizing similarity: ``p_normalized = scale * (transform @ [p, 1])``.

    Attributes:
        transform: [3, 4] float64 rigid transform (rotation, translation) of the original world.
        scale: positive scale applied after ``transform``.
    """

    transform: np.ndarray
    scale: float

    def apply_to_c2w(self, c2w: np.ndarray) -> np.ndarray:
        """[N,3|4,4] camera-to-world (any camera axes) -> [N,4,4] in the normalized world."""
        out = _homogeneous(np.asarray(c2w, np.float64))
        out = np.concatenate([self.transform @ out, out[:, 3:4]], axis=1)
        out[:, :3, 3] *= self.scale
        return out

    def apply_to_points(self, xyz: np.ndarray) -> np.ndarray:
        """[M,3] world points -> [M,3] normalized points."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        return self.scale * (xyz @ self.transform[:, :3].T + self.transform[:, 3])

    def invert_points(self, xyz: np.ndarray) -> np.ndarray:
        """[M,3] normalized points -> [M,3] original world points."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3) / self.scale
        return (xyz - self.transform[:, 3]) @ self.transform[:, :3]


def normalize_poses(
    c2w_opencv: np.ndarray,
    orientation_method: str = "up",
    center_method: str = "poses",
    auto_scale_poses: bool = True,
    applied_transform: np.ndarray | None = None,
) -> PoseNormalization:
    """nerfstudio's default normalization computed from OpenCV camera-to-world poses.

    Args:
        c2w_opencv: [N, 3|4, 4] camera-to-world, OpenCV camera axes, original world (all poses that share the world:
            train and eval together).
        applied_transform: optional [3, 4] applied before orienting (nerfstudio's COLMAP world permutation).
    Returns:
        The :class:`PoseNormalization`, whose ``transform`` includes ``applied_transform``.
    """
    poses = _homogeneous(np.asarray(c2w_opencv, np.float64))
    if poses.ndim != 3 or poses.shape[0] == 0:
        raise DataParserError("pose normalization needs at least one camera pose")
    if not np.isfinite(poses).all():
        bad = sorted(set(np.nonzero(~np.isfinite(poses).reshape(len(poses), -1).all(axis=1))[0].tolist()))
        raise DataParserError(f"camera poses {bad} contain NaN or inf: fix the scene's camera file")
    applied = np.eye(4)[:3] if applied_transform is None else np.asarray(applied_transform, np.float64)
    poses = np.concatenate([applied @ poses, poses[:, 3:4]], axis=1)
    oriented, transform = auto_orient_and_center_poses(opencv_to_opengl(poses), orientation_method, center_method)
    scale = 1.0
    if auto_scale_poses:
        extent = float(np.abs(oriented[:, :3, 3]).max())
        # A single camera (or cameras at one point) has no extent: keep unit scale rather than divide by zero.
        scale = 1.0 / extent if extent > 0 else 1.0
    full = transform @ np.concatenate([applied, np.array([[0.0, 0.0, 0.0, 1.0]])], axis=0)
    return PoseNormalization(transform=full, scale=scale)


def scene_scale_of(c2w_normalized: np.ndarray) -> float:
    """Half-width of the cube around the origin holding every (normalized) camera centre.

    With ``auto_scale_poses`` this is 1.0 by construction: the unit in which Splatfacto's size thresholds
    (densify/cull sizes) are expressed, so those thresholds are multiplied by it.
    """
    extent = float(np.abs(np.asarray(c2w_normalized)[:, :3, 3]).max())
    return extent if extent > 0 else 1.0


def c2w_to_viewmats(c2w_opencv: np.ndarray) -> torch.Tensor:
    """[N,4,4] camera-to-world (OpenCV) -> [N,4,4] float32 world-to-camera, computed in float64 then cast."""
    c2w = _homogeneous(np.asarray(c2w_opencv, np.float64))
    rot = c2w[:, :3, :3]
    w2c = np.zeros_like(c2w)
    w2c[:, :3, :3] = np.transpose(rot, (0, 2, 1))
    w2c[:, :3, 3] = -np.einsum("nji,nj->ni", rot, c2w[:, :3, 3])
    w2c[:, 3, 3] = 1.0
    return torch.from_numpy(w2c.astype(np.float32))


def make_cameras(c2w_opencv: np.ndarray, intrinsics: np.ndarray, widths: Any, heights: Any) -> Cameras:
    """Cameras from [N,4,4] OpenCV camera-to-world, [N,4] (fx, fy, cx, cy) and sizes [N]."""
    intrinsics = np.asarray(intrinsics, np.float64).reshape(-1, 4)
    ks = np.zeros((len(intrinsics), 3, 3))
    ks[:, 0, 0], ks[:, 1, 1], ks[:, 0, 2], ks[:, 1, 2] = intrinsics.T
    ks[:, 2, 2] = 1.0
    return Cameras(
        viewmats=c2w_to_viewmats(c2w_opencv),
        Ks=torch.from_numpy(ks.astype(np.float32)),
        widths=torch.as_tensor(np.asarray(widths), dtype=torch.int64).reshape(-1),
        heights=torch.as_tensor(np.asarray(heights), dtype=torch.int64).reshape(-1),
    )


# ----------------------------------------------------------------------------------------------------------------
# dataparser_transforms.json (nerfstudio's format)
# ----------------------------------------------------------------------------------------------------------------


def write_dataparser_transforms(path: str | Path, outputs_or_transform: Any, scale: float | None = None) -> Path:
    """Write nerfstudio's ``dataparser_transforms.json``: ``{"transform": [3x4], "scale": s}``, atomically.

    Args:
        path: the file to write (its folder is created).
        outputs_or_transform: a :class:`DataparserOutputs` (its transform and scale are used) or a [3,4] transform.
        scale: the scale, when a bare transform is given.
    """
    if isinstance(outputs_or_transform, DataparserOutputs):
        transform, scale = outputs_or_transform.dataparser_transform, outputs_or_transform.dataparser_scale
    else:
        transform = outputs_or_transform
        if scale is None:
            raise DataParserError("write_dataparser_transforms: give the scale with a bare transform")
    matrix = np.asarray(torch.as_tensor(transform, dtype=torch.float64).cpu().numpy(), np.float64)[:3, :4]
    payload = {"transform": matrix.tolist(), "scale": float(scale)}
    path = Path(path)
    atomic_write_text(path, json.dumps(payload, indent=4))
    return path


def read_dataparser_transforms(path: str | Path) -> PoseNormalization:
    """Read a ``dataparser_transforms.json`` back into a :class:`PoseNormalization`."""
    path = Path(path)
    try:
        payload = json.loads(path.read_text())
        transform = np.asarray(payload["transform"], np.float64)
        scale = float(payload["scale"])
    except FileNotFoundError:
        raise DataParserError(f"{path} does not exist: it is written by training into the run folder") from None
    except (KeyError, ValueError, TypeError) as exc:
        raise DataParserError(f"{path} is not a dataparser_transforms.json ({{'transform': 3x4, 'scale': s}}): {exc}") \
            from exc
    if transform.shape != (3, 4):
        raise DataParserError(f"{path}: 'transform' must be 3x4, got shape {transform.shape}")
    return PoseNormalization(transform=transform, scale=scale)


#: byte-order marks and the encodings they announce (UTF-32 before UTF-16: its LE mark starts with UTF-16's)
BYTE_ORDER_MARKS = (
    (b"\xef\xbb\xbf", "utf-8-sig"),
    (b"\xff\xfe\x00\x00", "utf-32"),
    (b"\x00\x00\xfe\xff", "utf-32"),
    (b"\xff\xfe", "utf-16"),
    (b"\xfe\xff", "utf-16"),
)


def read_text_file(path: Path) -> str:
    """The text of a scene's text file: UTF-8, or UTF-8/16/32 announced by a byte-order mark (the mark dropped);
    anything else is a :class:`DataParserError` naming the file and the reason. Line ends (LF, CRLF) are left to
    ``splitlines``."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataParserError(f"{path} cannot be read ({exc.strerror or exc})") from exc
    for mark, encoding in BYTE_ORDER_MARKS:
        if data.startswith(mark):
            try:
                return data.decode(encoding)
            except UnicodeDecodeError as exc:
                raise DataParserError(
                    f"{path} starts with a {encoding} byte-order mark but is not {encoding}: {exc}"
                ) from exc
    if b"\x00" in data:
        raise DataParserError(
            f"{path} holds NUL bytes: it looks like UTF-16 or UTF-32 without a byte-order mark; save it as UTF-8"
        )
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise DataParserError(
            f"{path} is not UTF-8 (byte 0x{data[exc.start]:02x} at offset {exc.start}): save it as UTF-8"
        ) from None


def _is_invisible(char: str) -> bool:
    return unicodedata.category(char) in ("Cf", "Cc")  # format (zero-width, BOM, bidi) and control characters


def _invisible(name: str) -> list[str]:
    """Code points of ``name`` that do not show when printed."""
    return [f"U+{ord(c):04X}" for c in name if _is_invisible(c)]


def _escaped(name: str) -> str:
    """``name`` with its invisible characters written as ``\\uXXXX``."""
    return "".join(f"\\u{ord(c):04x}" if _is_invisible(c) else c for c in name)


def read_split_list(path: Path) -> list[str]:
    """Basenames from a split list file, one a line (blank lines and ``#`` comments ignored); decoded by
    :func:`read_text_file` (UTF-8, or a byte-order mark's encoding).

    A name listed twice is an error naming the file, the name and its lines: training on it twice would silently
    weight that view double. A name holding an invisible character (a zero-width space, a stray byte-order mark) is
    an error showing it escaped: printed as is it would look like a valid name.
    """
    names: list[str] = []
    seen: dict[str, int] = {}
    for number, line in enumerate(read_text_file(path).splitlines(), start=1):
        line = line.strip()
        if line and not line.startswith("#"):
            hidden = _invisible(line)
            if hidden:
                shown = _escaped(line)
                raise DataParserError(
                    f"{path}:{number}: the name '{shown}' holds invisible character(s) {', '.join(hidden)}: "
                    "retype that line"
                )
            if line in seen:
                raise DataParserError(
                    f"{path}: '{line}' is listed twice (lines {seen[line]} and {number}): remove the duplicate"
                )
            seen[line] = number
            names.append(line)
    return names
