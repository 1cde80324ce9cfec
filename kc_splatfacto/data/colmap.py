"""COLMAP scenes: ``images/`` + a sparse model (``.bin`` or ``.txt``, read with pycolmap).

Layout::

    <scene>/images/            the images the model was built from (names as in images.txt, sub-folders allowed)
    <scene>/sparse/0/          cameras, images, points3D (.bin or .txt); also found at colmap/sparse/0 or sparse/

Splits (``eval_mode``, nerfstudio's names and rules, images in COLMAP image-id order as nerfstudio):
``interval`` every ``eval_interval``-th image (index % 8 == 0) is eval, the rest train (the default);
``fraction`` ``ceil(n * train_split_fraction)`` images evenly spaced over the sorted list train, the rest eval;
``filename`` names containing "train" are train, names containing "eval" are eval (others are an error);
``all`` every image in both splits. "val" and "test" are the same eval split.

Camera models PINHOLE, SIMPLE_PINHOLE, SIMPLE_RADIAL, RADIAL and OPENCV are supported; images of distorted models are
undistorted once with OpenCV (``getOptimalNewCameraMatrix`` with alpha 0, cropped to the valid region, as nerfstudio)
into a cached folder, so every camera handed on is a plain pinhole.
"""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import torch

from kc_splatfacto.data.base import (
    COLMAP_APPLIED_TRANSFORM,
    DataParser,
    DataParserConfig,
    DataParserError,
    empty_split_error,
    existing_folder,
    make_cameras,
    normalize_poses,
    scene_scale_of,
)
from kc_splatfacto.data.colmap_files import check_model_files, import_pycolmap
from kc_splatfacto.data.colmap_text import quaternion_rotation, read_text_model
from kc_splatfacto.data.images import (
    derived_is_fresh,
    derived_root,
    downscaled_paths,
    image_size,
    read_image,
    write_derived,
)
from kc_splatfacto.data.outputs import DataparserOutputs
from kc_splatfacto.data.paths import inside_folder
from kc_splatfacto.registry import DataParserSpecification
from kc_splatfacto.settings import integer, real, setting

# COLMAP model folders tried in order when none is configured (nerfstudio's default is colmap/sparse/0).
DEFAULT_MODEL_DIRS = ("sparse/0", "colmap/sparse/0", "sparse")
# Distortion of the supported models is kept in OpenCV's (k1, k2, p1, p2, k3) order.
SUPPORTED_CAMERA_MODELS = ("PINHOLE", "SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
EVAL_MODES = ("interval", "fraction", "filename", "all")


@dataclass
class ColmapCamera:
    """One COLMAP camera as a pinhole plus OpenCV distortion.

    Attributes:
        model: COLMAP model name.
        width, height: image size in pixels.
        fx, fy, cx, cy: intrinsics, pixel centres at +0.5 (COLMAP's convention).
        distortion: [5] OpenCV (k1, k2, p1, p2, k3), zeros for pinhole models.
    """

    model: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: np.ndarray

    @property
    def is_distorted(self) -> bool:
        return bool(np.any(self.distortion != 0.0))


@dataclass
class ColmapImage:
    """One registered image: its name (relative to the image folder), camera id and world-to-camera [4,4]."""

    name: str
    camera_id: int
    world_to_camera: np.ndarray


@dataclass
class ColmapModel:
    """What the parsers use from a COLMAP reconstruction.

    Attributes:
        path: the model folder.
        cameras: camera id -> :class:`ColmapCamera`.
        images: registered images in image-id order (nerfstudio's order for splits).
        points_xyz: [M,3] float64 world points; points_rgb: [M,3] uint8 colours.
    """

    path: Path
    cameras: dict[int, ColmapCamera]
    images: list[ColmapImage]
    points_xyz: np.ndarray
    points_rgb: np.ndarray
    by_name: dict[str, ColmapImage] = field(init=False)

    def __post_init__(self) -> None:
        self.by_name = {image.name: image for image in self.images}


def find_model_dir(scene: Path, configured: Path | None, candidates: tuple[str, ...] = DEFAULT_MODEL_DIRS) -> Path:
    """The COLMAP model folder of ``scene``: ``configured`` (relative to it) or the first candidate holding one."""
    if configured is not None:
        path = configured if Path(configured).is_absolute() else scene / configured
        if not has_model(path):
            raise DataParserError(
                f"no COLMAP model in {path}: expected cameras/images/points3D as .bin or .txt there "
                "(set colmap_path to the folder holding them)"
            )
        return path
    for candidate in candidates:
        if has_model(scene / candidate):
            return scene / candidate
    raise DataParserError(
        f"no COLMAP model found in {scene}: looked for cameras/images/points3D (.bin or .txt) in "
        f"{', '.join(candidates)}; run COLMAP or set colmap_path"
    )


def model_file(folder: Path, name: str) -> Path:
    """The ``name`` file (cameras, images, points3D) of the model in ``folder``: the .bin when present, else .txt."""
    binary = Path(folder) / f"{name}.bin"
    return binary if binary.is_file() else Path(folder) / f"{name}.txt"


def has_model(folder: Path) -> bool:
    """Whether ``folder`` holds cameras and images files of a COLMAP model (binary or text)."""
    return any(all((folder / f"{name}{ext}").is_file() for name in ("cameras", "images")) for ext in (".bin", ".txt"))


def _camera_from_pycolmap(camera_id: int, camera, model_dir: Path) -> ColmapCamera:
    model = camera.model.name if hasattr(camera.model, "name") else str(camera.model)
    p = [float(v) for v in camera.params]
    zero = np.zeros(5)
    if model == "PINHOLE":
        fx, fy, cx, cy = p
        dist = zero
    elif model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist = zero
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist = np.array([p[3], 0.0, 0.0, 0.0, 0.0])
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        dist = np.array([p[3], p[4], 0.0, 0.0, 0.0])
    elif model == "OPENCV":
        fx, fy, cx, cy = p[:4]
        dist = np.array([*p[4:8], 0.0])
    else:
        raise DataParserError(
            f"camera {camera_id} in {model_dir} uses the COLMAP camera model {model}, which is not supported: "
            f"supported models are {', '.join(SUPPORTED_CAMERA_MODELS)} (re-run COLMAP with one of them, "
            "or undistort the images with `colmap image_undistorter` first)"
        )
    values = np.array([fx, fy, cx, cy, *dist], np.float64)
    if not np.isfinite(values).all() or fx <= 0 or fy <= 0:
        raise DataParserError(f"camera {camera_id} in {model_dir} has invalid parameters {p}: fix the camera file")
    return ColmapCamera(model, int(camera.width), int(camera.height), fx, fy, cx, cy, dist)


def read_colmap_model(model_dir: Path, load_points: bool = True) -> ColmapModel:
    """Read a COLMAP model (binary or text) with pycolmap; a text model also without it (:mod:`colmap_text`).

    Clear errors for unsupported cameras, NaN poses, far-from-unit quaternions, duplicate image names and a missing
    points3D file; 3D points with NaN/inf coordinates are left out with one warning (binary and text alike).
    """
    model_dir = Path(model_dir)
    try:
        pycolmap = import_pycolmap()
    except ImportError as exc:  # a declared dependency, left out of some GPU images: text needs none
        if model_file(model_dir, "cameras").suffix == ".bin" or model_file(model_dir, "images").suffix == ".bin":
            raise ImportError(
                f"reading the binary COLMAP model in {model_dir} needs pycolmap: pip install pycolmap (or convert "
                "it to text with `colmap model_converter --output_type TXT`, which is read without pycolmap)"
            ) from exc
        pycolmap = None
    if not any((model_dir / f"points3D{ext}").is_file() for ext in (".bin", ".txt")):
        raise DataParserError(
            f"{model_dir} has cameras and images but no points3D.bin or points3D.txt: copy the model's points3D "
            "file there (COLMAP writes it with the model; an empty one gives random initial Gaussians)"
        )
    check_model_files(model_dir, SUPPORTED_CAMERA_MODELS)  # file, line and reason, before pycolmap's C++ reads it
    dropped_points: list[int] = []
    read = pycolmap.Reconstruction if pycolmap else read_text_model
    try:
        reconstruction = read(str(model_dir))
    except Exception as exc:
        bad = _images_with_non_finite_poses(model_dir / "images.txt")
        if bad:
            raise DataParserError(
                f"the poses of images {', '.join(bad)} in {model_dir / 'images.txt'} contain NaN/inf: "
                "fix or remove them"
            ) from exc
        dropped_points = _non_finite_point_lines(model_dir / "points3D.txt")
        if not dropped_points:
            raise DataParserError(f"could not read the COLMAP model in {model_dir}: {exc}") from exc
        reconstruction = _read_without_point_lines(read, model_dir, dropped_points)
    cameras = {cid: _camera_from_pycolmap(cid, cam, model_dir) for cid, cam in reconstruction.cameras.items()}
    for cid, camera in cameras.items():
        check_principal_point(camera, f"camera {cid} in {model_file(model_dir, 'cameras')}")
    images = []
    for _, image in sorted(reconstruction.images.items()):
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        w2c = np.eye(4)
        w2c[:3, :4] = np.asarray(pose.matrix(), np.float64)
        if not np.isfinite(w2c).all():
            raise DataParserError(
                f"the pose of image '{image.name}' in {model_dir} contains NaN/inf: fix images.txt/.bin"
            )
        w2c[:3, :3] = _unit_rotation(np.asarray(pose.rotation.quat, np.float64), image, model_dir)
        if image.camera_id not in cameras:
            raise DataParserError(f"image '{image.name}' in {model_dir} names unknown camera {image.camera_id}")
        images.append(ColmapImage(image.name, int(image.camera_id), w2c))
    names = [image.name for image in images]
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise DataParserError(
            f"{model_file(model_dir, 'images')} registers {', '.join(twice)} more than once: keep one pose per image"
        )
    if load_points and len(reconstruction.points3D) > 0:
        points = list(reconstruction.points3D.values())
        xyz = np.array([p.xyz for p in points], np.float64).reshape(-1, 3)
        rgb = np.array([p.color for p in points], np.uint8).reshape(-1, 3)
        finite = np.isfinite(xyz).all(axis=1)
        if not finite.all():
            warnings.warn(
                f"{model_dir}: {int((~finite).sum())} 3D points with NaN/inf coordinates were left out",
                stacklevel=2,
            )
            xyz, rgb = xyz[finite], rgb[finite]
    else:
        xyz, rgb = np.zeros((0, 3)), np.zeros((0, 3), np.uint8)
    if dropped_points and load_points:
        shown = ", ".join(str(n) for n in dropped_points[:10]) + (" ..." if len(dropped_points) > 10 else "")
        warnings.warn(
            f"{model_dir / 'points3D.txt'}: {len(dropped_points)} 3D points with NaN/inf coordinates were left out "
            f"(lines {shown})", stacklevel=2
        )
    if len(xyz) and images:
        warn_points_behind_cameras(xyz, [image.world_to_camera for image in images], model_file(model_dir, "points3D"))
    return ColmapModel(model_dir, cameras, images, xyz, rgb)


#: a principal point farther than this many image sizes outside the image cannot be a real camera's
PRINCIPAL_POINT_FAR = 1.0


def check_principal_point(camera: ColmapCamera, where: str) -> None:
    """An error when the principal point lies more than an image size outside the image, a warning when it lies
    outside it at all (a crop can do that; a wrong unit or a swapped cx/cy usually did)."""
    w, h = camera.width, camera.height
    inside = 0.0 <= camera.cx <= w and 0.0 <= camera.cy <= h
    near = (-PRINCIPAL_POINT_FAR * w <= camera.cx <= (1 + PRINCIPAL_POINT_FAR) * w
            and -PRINCIPAL_POINT_FAR * h <= camera.cy <= (1 + PRINCIPAL_POINT_FAR) * h)
    text = f"{where}: the principal point ({camera.cx:g}, {camera.cy:g}) is outside the {w}x{h} image"
    if not near:
        raise DataParserError(
            f"{text}, by more than the image's size: cx, cy are in pixels of that image (check the unit, a swapped "
            "cx/cy, or a size that does not belong to this camera)"
        )
    if not inside:
        warnings.warn(
            f"{text}: the views are rendered as given; check cx, cy if the images were not cropped",
            stacklevel=2,
        )


#: warn when more than this share of the seed points lies behind every camera
BEHIND_SHARE_WARNING = 0.5


def warn_points_behind_cameras(xyz: np.ndarray, world_to_cameras: list[np.ndarray], source: Path) -> int:
    """Warn with counts when most seed points [M, 3] are behind every camera (their depth z <= 0 in each): points and
    poses in different conventions. Returns how many are behind every camera."""
    w2c = np.stack(world_to_cameras)  # [N, 4, 4]
    behind_all = np.ones(len(xyz), bool)
    for start in range(0, len(w2c), 64):  # [M, chunk] depths, bounded memory
        block = w2c[start:start + 64]
        depth = xyz @ block[:, 2, :3].T + block[:, 2, 3]
        behind_all &= ~(depth > 0).any(axis=1)
    count = int(behind_all.sum())
    if count > BEHIND_SHARE_WARNING * len(xyz):
        warnings.warn(
            f"{source}: {count} of {len(xyz)} seed points are behind every camera: the points and the poses may be in "
            "different conventions (the Gaussians starting there will not be seen)", stacklevel=2
        )
    return count


#: A quaternion whose norm is this close to 1 is rounding (text models print ~16 digits): normalized silently.
#: Farther from 1 the file is broken (a rotation scaled by |q|^2 would shear every ray): an error.
QUATERNION_NORM_TOLERANCE = 1e-3


def _unit_rotation(quat_xyzw: np.ndarray, image, model_dir: Path) -> np.ndarray:
    """[3,3] rotation of a COLMAP quaternion (pycolmap's x, y, z, w order), normalized; an error when far from unit."""
    norm = float(np.linalg.norm(quat_xyzw))
    if not abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
        where = model_file(model_dir, "images")
        line = _images_txt_line(where, image.image_id) if where.suffix == ".txt" else None
        at = f"{where}:{line}" if line is not None else str(where)
        raise DataParserError(
            f"{at}: the rotation quaternion of image '{image.name}' has norm {norm:.6g}, not 1 (tolerance "
            f"{QUATERNION_NORM_TOLERANCE:g}): the pose is not a rotation; fix QW QX QY QZ of that image"
        )
    return quaternion_rotation(quat_xyzw / norm)


def _images_txt_line(images_txt: Path, image_id: int) -> int | None:
    """1-based line number of image ``image_id``'s pose line in ``images.txt``."""
    data_lines = 0
    for number, line in enumerate(images_txt.read_text(errors="replace").splitlines(), start=1):
        if line.startswith("#"):
            continue
        if data_lines % 2 == 0:
            fields = line.split()
            if fields and fields[0] == str(image_id):
                return number
        data_lines += 1
    return None


def _non_finite_point_lines(points_txt: Path) -> list[int]:
    """1-based numbers of the lines of ``points3D.txt`` whose X Y Z hold NaN/inf (pycolmap's reader rejects them)."""
    if not points_txt.is_file():
        return []
    bad = []
    for number, line in enumerate(points_txt.read_text(errors="replace").splitlines(), start=1):
        fields = line.split()
        if not fields or line.startswith("#") or len(fields) < 4:
            continue
        try:
            finite = np.isfinite([float(v) for v in fields[1:4]]).all()
        except ValueError:
            continue
        if not finite:
            bad.append(number)
    return bad


def _read_without_point_lines(read, model_dir: Path, skip_lines: list[int]):
    """The text model of ``model_dir`` read with the ``points3D.txt`` lines ``skip_lines`` left out (a temp copy)."""
    skip = set(skip_lines)
    with tempfile.TemporaryDirectory(prefix="kc_colmap_") as tmp:
        for path in model_dir.iterdir():
            if path.is_file() and path.name != "points3D.txt":
                shutil.copyfile(path, Path(tmp) / path.name)
        kept = [
            line
            for number, line in enumerate((model_dir / "points3D.txt").read_text().splitlines(), start=1)
            if number not in skip
        ]
        (Path(tmp) / "points3D.txt").write_text("\n".join(kept) + "\n")
        try:
            return read(tmp)
        except Exception as exc:
            raise DataParserError(f"could not read the COLMAP model in {model_dir}: {exc}") from exc


def _images_with_non_finite_poses(images_txt: Path) -> list[str]:
    """Names of images whose pose line holds a non-finite number (pycolmap's text reader only says it failed)."""
    if not images_txt.is_file():
        return []
    bad = []
    lines = [line for line in images_txt.read_text(errors="replace").splitlines() if not line.startswith("#")]
    for line in lines[0::2]:  # pose lines alternate with 2D point lines
        fields = line.split()
        if len(fields) < 10:
            continue
        try:
            finite = bool(np.isfinite([float(v) for v in fields[1:8]]).all())
        except ValueError:
            finite = False
        if not finite:
            bad.append(fields[9])
    return bad


# ----------------------------------------------------------------------------------------------------------------
# Undistortion
# ----------------------------------------------------------------------------------------------------------------


def undistorted_pinhole(camera: ColmapCamera) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """The pinhole that OpenCV undistorts ``camera`` into, and the valid-pixel crop.

    Returns:
        (new_k [3,3] for the full frame, roi (x, y, w, h)); pixel centres at +0.5 like COLMAP.
    """
    k_cv = _k_opencv(camera)
    new_k, roi = cv2.getOptimalNewCameraMatrix(k_cv, camera.distortion, (camera.width, camera.height), 0)
    x, y, w, h = (int(v) for v in roi)
    if w <= 0 or h <= 0:
        raise DataParserError(
            f"undistorting a {camera.model} camera with distortion {camera.distortion.tolist()} leaves no valid "
            "pixels: "
            "check the camera parameters"
        )
    new_k = np.asarray(new_k, np.float64).copy()
    new_k[0, 2] += 0.5 - x
    new_k[1, 2] += 0.5 - y
    return new_k, (x, y, w, h)


def _k_opencv(camera: ColmapCamera) -> np.ndarray:
    """OpenCV puts pixel centres at integer coordinates: shift the principal point by -0.5 for its functions."""
    return np.array([[camera.fx, 0.0, camera.cx - 0.5], [0.0, camera.fy, camera.cy - 0.5], [0.0, 0.0, 1.0]])


def undistort_image(image: np.ndarray, camera: ColmapCamera) -> np.ndarray:
    """[H,W,C] image of a distorted ``camera`` -> cropped pinhole image of :func:`undistorted_pinhole`."""
    new_k, (x, y, w, h) = undistorted_pinhole(camera)
    new_k_cv = new_k.copy()
    new_k_cv[0, 2] += x - 0.5
    new_k_cv[1, 2] += y - 0.5
    out = cv2.undistort(image, _k_opencv(camera), camera.distortion, None, new_k_cv)
    return np.ascontiguousarray(out[y : y + h, x : x + w])


def undistorted_paths(
    image_paths: list[Path], cameras: list[ColmapCamera], images_dir: Path, cache_dir: Path | None
) -> tuple[list[Path], Path]:
    """Undistorted copies of distorted images (created once, reused), and the folder holding them.

    The folder name carries a hash of the camera parameters, so an edited model never reuses stale images.
    """
    params = sorted({(c.model, c.width, c.height, c.fx, c.fy, c.cx, c.cy, *c.distortion.tolist()) for c in cameras})
    digest = hashlib.sha1(json.dumps(params).encode()).hexdigest()[:8]
    folder = derived_root(images_dir, cache_dir) / f"{images_dir.name}_undistorted_{digest}"
    out = []
    for path, camera in zip(image_paths, cameras):
        relative = Path(path).relative_to(images_dir)
        # Undistorted copies are lossless PNGs: a JPEG round trip would add artefacts to the training targets.
        target = folder / relative.with_suffix(".png")
        if camera.is_distorted and not derived_is_fresh(target, path, folder):
            write_derived(target, undistort_image(read_image(path), camera), path, folder)
        out.append(target if camera.is_distorted else Path(path))
    return out, folder


# ----------------------------------------------------------------------------------------------------------------
# Shared assembly for COLMAP-based parsers (COLMAP, SPARS3R)
# ----------------------------------------------------------------------------------------------------------------


def image_folder(scene: Path, images_path: Path) -> Path:
    """The image folder ``images_path`` (a config's, relative to ``scene``), checked to be a folder."""
    return existing_folder(scene / images_path, "image folder", "set images_path to the scene's image folder")


def check_image_sizes(paths: list[Path], cameras: list[ColmapCamera], camera_names: list[str]) -> None:
    """Each image must have its camera's size; names the first offender."""
    for path, camera, camera_name in zip(paths, cameras, camera_names):
        width, height = image_size(path)
        if (width, height) != (camera.width, camera.height):
            raise DataParserError(
                f"image {path} is {width}x{height} but its {camera_name} is {camera.width}x{camera.height}: "
                "images of one camera must all have the camera's size (use the images the cameras were calibrated on)"
            )


def pinhole_images(
    config: DataParserConfig, paths: list[Path], cameras: list[ColmapCamera], images_dirs: list[Path], metadata: dict
) -> tuple[list[Path], np.ndarray, np.ndarray]:
    """Undistort (distorted cameras) then downscale the split's images, with matching pinhole intrinsics.

    Args:
        paths: [N] image files; cameras: [N] their cameras; images_dirs: [N] the folder each path is relative to
            (derived copies keep that relative path).
    Returns:
        (image paths to load, [N,4] fx, fy, cx, cy, [N,2] width, height).
    """
    if config.downscale_factor > 1:  # before any image is undistorted or resized: nothing half-written
        pinhole_sizes = [undistorted_pinhole(c)[1][2:] if c.is_distorted else (c.width, c.height) for c in cameras]
        scale_intrinsics(np.zeros((len(cameras), 4)), np.asarray(pinhole_sizes).reshape(-1, 2), config.downscale_factor)
    intrinsic_rows: list[list[float]] = []
    size_rows: list[tuple[int, int]] = []
    out_paths = []
    for path, camera, images_dir in zip(paths, cameras, images_dirs):
        if camera.is_distorted:
            new_k, (_, _, w, h) = undistorted_pinhole(camera)
            intrinsic_rows.append([new_k[0, 0], new_k[1, 1], new_k[0, 2], new_k[1, 2]])
            size_rows.append((w, h))
            undistorted, folder = undistorted_paths([path], [camera], images_dir, config.cache_dir)
            if folder not in metadata.setdefault("undistorted_dirs", []):
                metadata["undistorted_dirs"].append(folder)
            path, images_dir = undistorted[0], folder
        else:
            intrinsic_rows.append([camera.fx, camera.fy, camera.cx, camera.cy])
            size_rows.append((camera.width, camera.height))
        if config.downscale_factor > 1:
            path = downscaled_paths([path], images_dir, config.downscale_factor, config.cache_dir)[0]
        out_paths.append(path)
    intrinsics = np.asarray(intrinsic_rows, np.float64).reshape(-1, 4)
    sizes = np.asarray(size_rows, np.int64).reshape(-1, 2)
    if config.downscale_factor > 1:
        intrinsics, sizes = scale_intrinsics(intrinsics, sizes, config.downscale_factor)
    return out_paths, intrinsics, sizes


def colmap_split_outputs(
    config: DataParserConfig,
    model: ColmapModel,
    images_dir: Path,
    normalize_names: list[str],
    split_names: list[str],
    split: str,
    load_points: bool,
    metadata: dict,
) -> DataparserOutputs:
    """Normalize on ``normalize_names`` (train + eval), then build the outputs of ``split_names``.

    Only the split's images are checked, undistorted and downscaled.
    """
    if not split_names:  # before any image is read or derived
        raise empty_split_error(config, split)
    for name in normalize_names:  # names come from a file someone sent: they must stay inside the image folder
        inside_folder(images_dir, name, f"image name in {model_file(model.path, 'images')}", config.allow_symlinks_out)
    missing = [name for name in split_names if not (images_dir / name).is_file()]
    if missing:
        raise DataParserError(
            f"{len(missing)} image(s) of split '{split}' are missing from {images_dir}: {', '.join(missing[:10])}"
            f"{' ...' if len(missing) > 10 else ''} (add the files or remove them from the model / split list)"
        )
    c2w_all = np.stack([np.linalg.inv(model.by_name[name].world_to_camera) for name in normalize_names])
    normalization = normalize_poses(
        c2w_all,
        config.orientation_method,
        config.center_method,
        config.auto_scale_poses,
        applied_transform=COLMAP_APPLIED_TRANSFORM,
    )
    c2w_normalized_all = normalization.apply_to_c2w(c2w_all)
    index = {name: i for i, name in enumerate(normalize_names)}
    c2w = c2w_normalized_all[[index[name] for name in split_names]]

    camera_ids = [model.by_name[name].camera_id for name in split_names]
    cameras = [model.cameras[cid] for cid in camera_ids]
    paths = [images_dir / name for name in split_names]
    check_image_sizes(paths, cameras, [f"COLMAP camera {cid}" for cid in camera_ids])
    mask_paths = None
    masks_path = getattr(config, "masks_path", None)
    if masks_path is not None:
        masks_dir = Path(config.data) / masks_path
        mask_paths = [masks_dir / Path(name).with_suffix(".png") for name in split_names]
        mask_paths = prepare_masks(config, mask_paths, cameras, [masks_dir] * len(paths), metadata)
    paths, intrinsics, sizes = pinhole_images(config, paths, cameras, [images_dir] * len(paths), metadata)

    outputs = DataparserOutputs(
        image_filenames=paths,
        cameras=make_cameras(c2w, intrinsics, sizes[:, 0], sizes[:, 1]),
        split=split,
        scene_scale=scene_scale_of(c2w_normalized_all),
        dataparser_transform=torch.from_numpy(normalization.transform.astype(np.float32)),
        dataparser_scale=float(normalization.scale),
        mask_filenames=mask_paths,
        metadata={"normalization": normalization, "image_names": list(split_names), **metadata},
    )
    if load_points and len(model.points_xyz) > 0:
        outputs.points3d_xyz = torch.from_numpy(normalization.apply_to_points(model.points_xyz).astype(np.float32))
        outputs.points3d_rgb = torch.from_numpy(model.points_rgb.copy())
    return outputs


def prepare_masks(
    config: DataParserConfig,
    mask_paths: list[Path],
    cameras: list[ColmapCamera],
    masks_dirs: list[Path],
    metadata: dict,
) -> list[Path]:
    """Mask files (white = use the pixel) checked, then undistorted and downscaled exactly like their images."""
    missing = [str(p) for p in mask_paths if not p.is_file()]
    if missing:
        raise DataParserError(
            f"{len(missing)} mask file(s) are missing: {', '.join(missing[:5])}{' ...' if len(missing) > 5 else ''} "
            "(masks are <masks_path>/<image name>.png; add them or unset masks_path / mask_path)"
        )
    check_image_sizes(mask_paths, cameras, ["camera"] * len(mask_paths))
    paths, _, _ = pinhole_images(config, mask_paths, cameras, masks_dirs, {})
    return paths


def scale_intrinsics(intrinsics: np.ndarray, sizes: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """[N,4] (fx, fy, cx, cy) and [N,2] (w, h) for images downscaled by ``factor`` (floor sizes, exact ratios)."""
    sizes = np.asarray(sizes, np.int64)
    new_sizes = sizes // factor
    if (new_sizes < 1).any():
        raise DataParserError(
            f"downscale_factor {factor} is too large for the {sizes.min()}-pixel images: use a smaller one"
        )
    ratio = new_sizes / sizes
    out = np.asarray(intrinsics, np.float64).copy()
    out[:, 0] *= ratio[:, 0]
    out[:, 2] *= ratio[:, 0]
    out[:, 1] *= ratio[:, 1]
    out[:, 3] *= ratio[:, 1]
    return out, new_sizes


# ----------------------------------------------------------------------------------------------------------------
# The COLMAP dataparser
# ----------------------------------------------------------------------------------------------------------------


@dataclass
class ColmapDataParserConfig(DataParserConfig):
    """A COLMAP scene: ``images/`` + ``sparse/0/`` (see the module docstring for splits and camera models)."""

    images_path: Path = Path("images")
    """Image folder, relative to ``data``."""
    colmap_path: Path | None = None
    """Model folder relative to ``data``; None tries sparse/0, colmap/sparse/0, sparse."""
    eval_mode: Literal["interval", "fraction", "filename", "all"] = "interval"
    """"interval", "fraction", "filename" or "all" (nerfstudio's)."""
    eval_interval: int = setting(8, integer(1))
    """Every ``eval_interval``-th image is eval (eval_mode "interval")."""
    train_split_fraction: float = setting(0.9, real(0.0, 1.0, low_open=True))
    """Fraction of images for training (eval_mode "fraction")."""
    load_3d_points: bool = True
    """Seed points from points3D."""
    masks_path: Path | None = None
    """Optional mask folder relative to ``data``: ``<masks_path>/<image name>.png``, white = use the pixel."""

    def setup(self) -> ColmapDataParser:
        return ColmapDataParser(self)


def split_indices(
    names: list[str], eval_mode: str, eval_interval: int, train_fraction: float
) -> tuple[list[int], list[int]]:
    """(train, eval) indices into ``names`` in the model's order (nerfstudio's ``get_train_eval_split_*``)."""
    n = len(names)
    if eval_mode == "interval":
        if eval_interval < 1:
            raise DataParserError(f"eval_interval must be >= 1, got {eval_interval}")
        return [i for i in range(n) if i % eval_interval != 0], [i for i in range(n) if i % eval_interval == 0]
    if eval_mode == "fraction":
        if not 0.0 < train_fraction <= 1.0:
            raise DataParserError(f"train_split_fraction must be in (0, 1], got {train_fraction}")
        num_train = math.ceil(n * train_fraction)
        train = sorted(set(np.linspace(0, n - 1, num_train, dtype=int).tolist()))
        return train, [i for i in range(n) if i not in set(train)]
    if eval_mode == "filename":
        train, evals = [], []
        for i, name in enumerate(names):
            base = Path(name).name
            if "train" in base:
                train.append(i)
            elif "eval" in base:
                evals.append(i)
            else:
                raise DataParserError(
                    f"eval_mode 'filename' needs 'train' or 'eval' in every image name, but '{name}' has neither: "
                    "rename the images or use eval_mode 'interval'"
                )
        return train, evals
    if eval_mode == "all":
        return list(range(n)), list(range(n))
    raise DataParserError(f"unknown eval_mode '{eval_mode}': use one of {', '.join(EVAL_MODES)}")


class ColmapDataParser(DataParser):
    config: ColmapDataParserConfig
    scene_name = "COLMAP scene folder"

    def _generate_dataparser_outputs(self, split: str) -> DataparserOutputs:
        scene = Path(self.config.data)
        images_dir = image_folder(scene, self.config.images_path)
        model_dir = find_model_dir(scene, self.config.colmap_path)
        model = self.memo(("colmap", model_dir), read_colmap_model, model_dir, self.config.load_3d_points)
        if not model.images:
            raise DataParserError(f"the COLMAP model in {model.path} has no registered images")
        names = [image.name for image in model.images]
        train, evals = split_indices(
            names, self.config.eval_mode, self.config.eval_interval, self.config.train_split_fraction
        )
        chosen = train if split == "train" else evals
        return colmap_split_outputs(
            self.config,
            model,
            images_dir,
            normalize_names=names,
            split_names=[names[i] for i in chosen],
            split=split,
            load_points=self.config.load_3d_points,
            metadata={"format": "colmap", "model_dir": model.path, "eval_mode": self.config.eval_mode},
        )


def _spec():
    return DataParserSpecification(
        config=ColmapDataParserConfig(),
        description="COLMAP scene: images/ + sparse/0 (.bin or .txt); eval modes interval/fraction/filename/all",
    )


colmap_dataparser = _spec()
