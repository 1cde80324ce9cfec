"""COLMAP model files checked before pycolmap reads them.

pycolmap's C++ reader reports a bad model in its own terms ("Rig with ID 7 does not exist", "unordered_map::at",
"vector::_M_range_check") or not at all. :func:`check_model_files` reads the structure first, in COLMAP's own layout
(``colmap/src/colmap/scene/reconstruction_io.cc``), and names the file, the line (text) or the record and byte offset
(binary), and what is wrong:

- cameras: a known model with its number of parameters, a positive size and focal length, finite values;
- images: the pose line's fields (id, quaternion, translation, camera id, name), a camera that exists, the 2D-points
  line after each pose line (possibly empty) of X Y POINT3D_ID triples;
- points3D: id, X Y Z, R G B in 0..255, error, then (IMAGE_ID POINT2D_IDX) pairs naming registered images.

Non-finite point coordinates are left to :func:`kc_splatfacto.data.colmap.read_colmap_model`, which drops those
points with a warning.
"""

from __future__ import annotations

import math
import signal
import struct
import threading
from pathlib import Path
from types import ModuleType

from kc_splatfacto.data.base import DataParserError, read_text_file

#: every COLMAP camera model: name -> (model id in .bin files, number of parameters)
COLMAP_CAMERA_MODELS = {
    "SIMPLE_PINHOLE": (0, 3),
    "PINHOLE": (1, 4),
    "SIMPLE_RADIAL": (2, 4),
    "RADIAL": (3, 5),
    "OPENCV": (4, 8),
    "OPENCV_FISHEYE": (5, 8),
    "FULL_OPENCV": (6, 12),
    "FOV": (7, 5),
    "SIMPLE_RADIAL_FISHEYE": (8, 4),
    "RADIAL_FISHEYE": (9, 5),
    "THIN_PRISM_FISHEYE": (10, 12),
    "RAD_TAN_THIN_PRISM_FISHEYE": (11, 16),
}
MODEL_NAMES = {model_id: name for name, (model_id, _) in COLMAP_CAMERA_MODELS.items()}
#: models whose first parameter is the one focal length (the others have fx, fy first)
SINGLE_FOCAL_MODELS = ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL", "FOV", "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE")
INVALID_POINT3D_ID = -1


def _unsupported_model(name: str, supported: tuple[str, ...], where: str) -> DataParserError:
    return DataParserError(
        f"{where}: the camera uses the COLMAP camera model {name}, which is not supported: supported models are "
        f"{', '.join(supported)} (re-run COLMAP "
        "with one of them, or undistort the images with `colmap image_undistorter` first)"
    )


def _check_camera(name: str, width: float, height: float, params: list[float], supported: tuple[str, ...],
                  where: str) -> None:
    if name not in COLMAP_CAMERA_MODELS:
        raise DataParserError(
            f"{where}: '{name}' is not a COLMAP camera model (COLMAP's are {', '.join(COLMAP_CAMERA_MODELS)})"
        )
    expected = COLMAP_CAMERA_MODELS[name][1]
    if len(params) != expected:
        raise DataParserError(f"{where}: a {name} camera has {expected} parameters, this line gives {len(params)}")
    if name not in supported:
        raise _unsupported_model(name, supported, where)
    if not (width >= 1 and height >= 1):
        raise DataParserError(f"{where}: the image size {width}x{height} must be positive")
    if not all(math.isfinite(p) for p in params):
        raise DataParserError(f"{where}: the camera parameters {params} must be finite")
    focals = params[:1] if name in SINGLE_FOCAL_MODELS else params[:2]
    if any(f <= 0 for f in focals):
        raise DataParserError(f"{where}: the focal length {focals} must be > 0 (the first parameters of {name})")


def _number(text: str, kind: type, where: str, what: str):
    try:
        value = kind(text)
    except ValueError:
        raise DataParserError(f"{where}: {what} must be {'an integer' if kind is int else 'a number'}, got '{text}'") from None
    return value


# ------------------------------------------------------------------------------------------------ text models


def _data_lines(path: Path) -> list[tuple[int, str]]:
    """(1-based line number, stripped text) of every line, comments included (their handling differs per file)."""
    return [(n, line.strip()) for n, line in enumerate(read_text_file(path).splitlines(), start=1)]


def check_cameras_txt(path: Path, supported: tuple[str, ...]) -> set[int]:
    """The camera ids of ``cameras.txt``, every line checked."""
    ids: set[int] = set()
    for number, line in _data_lines(path):
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{number}"
        fields = line.split()
        if len(fields) < 4:
            raise DataParserError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[], got {len(fields)} fields")
        camera_id = _number(fields[0], int, where, "CAMERA_ID")
        width, height = (_number(v, int, where, "WIDTH/HEIGHT") for v in fields[2:4])
        params = [_number(v, float, where, "a camera parameter") for v in fields[4:]]
        _check_camera(fields[1], width, height, params, supported, where)
        if camera_id in ids:
            raise DataParserError(f"{where}: camera {camera_id} is defined twice")
        ids.add(camera_id)
    return ids


def check_images_txt(path: Path, camera_ids: set[int], point_ids: set[int] | None) -> set[int]:
    """The image ids of ``images.txt``; each pose line and the 2D-points line after it checked."""
    lines = _data_lines(path)
    ids: set[int] = set()
    i = 0
    while i < len(lines):
        number, line = lines[i]
        if not line or line.startswith("#"):
            i += 1
            continue
        where = f"{path}:{number}"
        fields = line.split()
        if len(fields) < 10:
            raise DataParserError(
                f"{where}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, got {len(fields)} fields"
            )
        image_id = _number(fields[0], int, where, "IMAGE_ID")
        for value in fields[1:8]:
            _number(value, float, where, "QW QX QY QZ TX TY TZ")
        camera_id = _number(fields[8], int, where, "CAMERA_ID")
        name = " ".join(fields[9:])
        if camera_id not in camera_ids:
            raise DataParserError(
                f"{where}: image '{name}' names camera {camera_id}, which cameras.txt does not define (it has "
                f"{', '.join(map(str, sorted(camera_ids))) or 'none'})"
            )
        if image_id in ids:
            raise DataParserError(f"{where}: image id {image_id} is used twice")
        ids.add(image_id)
        if i + 1 >= len(lines):
            raise DataParserError(
                f"{where}: image '{name}' has no 2D-points line after it: each image takes two lines in images.txt "
                "(the second, its X Y POINT3D_ID triples, may be empty)"
            )
        points_number, points_line = lines[i + 1]
        values = points_line.split()
        points_where = f"{path}:{points_number}"
        if len(values) % 3 != 0:
            raise DataParserError(
                f"{points_where}: expected the 2D points of image '{name}' (X Y POINT3D_ID triples; each image takes "
                f"two lines, the second may be empty), got {len(values)} values: is the 2D-points line missing?"
            )
        for k in range(0, len(values), 3):
            _number(values[k], float, points_where, "a 2D point's X")
            _number(values[k + 1], float, points_where, "a 2D point's Y")
            point_id = _number(values[k + 2], int, points_where, "POINT3D_ID")
            if point_ids is not None and point_id != INVALID_POINT3D_ID and point_id not in point_ids:
                raise DataParserError(
                    f"{points_where}: image '{name}' observes 3D point {point_id}, which points3D.txt does not hold"
                )
        i += 2
    return ids


def check_points3d_txt(path: Path, image_ids: set[int] | None) -> None:
    for number, line in _data_lines(path):
        if not line or line.startswith("#"):
            continue
        where = f"{path}:{number}"
        fields = line.split()
        if len(fields) < 8 or (len(fields) - 8) % 2:
            raise DataParserError(
                f"{where}: expected POINT3D_ID X Y Z R G B ERROR then (IMAGE_ID POINT2D_IDX) pairs, got "
                f"{len(fields)} fields"
            )
        _number(fields[0], int, where, "POINT3D_ID")
        for value in fields[1:4]:
            _number(value, float, where, "X Y Z")  # NaN/inf: dropped later with a warning
        for value in fields[4:7]:
            colour = _number(value, int, where, "R G B")
            if not 0 <= colour <= 255:
                raise DataParserError(f"{where}: the colour R G B {' '.join(fields[4:7])} must be integers in 0..255")
        _number(fields[7], float, where, "ERROR")
        for k in range(8, len(fields), 2):
            image_id = _number(fields[k], int, where, "a track's IMAGE_ID")
            _number(fields[k + 1], int, where, "a track's POINT2D_IDX")
            if image_ids is not None and image_id not in image_ids:
                raise DataParserError(f"{where}: the track names image {image_id}, which images.txt does not hold")


# ------------------------------------------------------------------------------------------------ binary models


class _Reader:
    """Sequential struct reads that name the file, the record and the byte offset when the data ends early."""

    def __init__(self, path: Path):
        self.path = path
        self.data = path.read_bytes()
        self.offset = 0

    def read(self, fmt: str, what: str):
        size = struct.calcsize(fmt)
        if self.offset + size > len(self.data):
            raise DataParserError(
                f"{self.path} is truncated: {what} needs bytes {self.offset}..{self.offset + size} but the file has "
                f"{len(self.data)} bytes (copy the model again, or re-export it with COLMAP)"
            )
        values = struct.unpack_from(fmt, self.data, self.offset)
        self.offset += size
        return values

    def skip(self, size: int, what: str) -> None:
        if self.offset + size > len(self.data):
            raise DataParserError(
                f"{self.path} is truncated: {what} needs bytes {self.offset}..{self.offset + size} but the file has "
                f"{len(self.data)} bytes (copy the model again, or re-export it with COLMAP)"
            )
        self.offset += size

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise DataParserError(f"{self.path} is truncated: {what} has no end (the file ends inside it)")
        text = self.data[self.offset:end].decode("utf-8", errors="replace")
        self.offset = end + 1
        return text

    def finish(self) -> None:
        if self.offset != len(self.data):
            raise DataParserError(
                f"{self.path} has {len(self.data) - self.offset} bytes after its last record: the file is damaged "
                "(copy the model again, or re-export it with COLMAP)"
            )


def check_cameras_bin(path: Path, supported: tuple[str, ...]) -> set[int]:
    reader = _Reader(path)
    (count,) = reader.read("<Q", "the camera count")
    ids = set()
    for k in range(count):
        what = f"camera {k + 1} of {count}"
        camera_id, model_id, width, height = reader.read("<iiQQ", what)
        if model_id not in MODEL_NAMES:
            raise DataParserError(f"{path}: {what} (id {camera_id}) has model id {model_id}, not a COLMAP camera model")
        name = MODEL_NAMES[model_id]
        params = list(reader.read(f"<{COLMAP_CAMERA_MODELS[name][1]}d", what))
        _check_camera(name, width, height, params, supported, f"{path}: camera {camera_id}")
        ids.add(camera_id)
    reader.finish()
    return ids


def check_images_bin(path: Path, camera_ids: set[int]) -> set[int]:
    reader = _Reader(path)
    (count,) = reader.read("<Q", "the image count")
    ids = set()
    for k in range(count):
        what = f"image {k + 1} of {count}"
        image_id = reader.read("<I", what)[0]
        reader.read("<7d", what)
        (camera_id,) = reader.read("<I", what)
        name = reader.name(f"the name of {what}")
        if camera_id not in camera_ids:
            raise DataParserError(
                f"{path}: image '{name}' names camera {camera_id}, which cameras.bin does not define (it has "
                f"{', '.join(map(str, sorted(camera_ids))) or 'none'})"
            )
        (num_points,) = reader.read("<Q", f"the 2D point count of image '{name}'")
        reader.skip(num_points * 24, f"the {num_points} 2D points of image '{name}'")
        ids.add(image_id)
    reader.finish()
    return ids


def check_points3d_bin(path: Path, image_ids: set[int]) -> None:
    reader = _Reader(path)
    (count,) = reader.read("<Q", "the point count")
    for k in range(count):
        what = f"3D point {k + 1} of {count}"
        reader.skip(8 + 24 + 3 + 8, what)
        (track_length,) = reader.read("<Q", f"the track length of {what}")
        track = reader.read(f"<{2 * track_length}I", f"the track of {what}") if track_length else ()
        unknown = [i for i in track[0::2] if i not in image_ids]
        if unknown:
            raise DataParserError(f"{path}: the track of {what} names image {unknown[0]}, which images.bin does not hold")
    reader.finish()


# ------------------------------------------------------------------------------------------------ the model


def check_model_files(model_dir: Path, supported: tuple[str, ...]) -> None:
    """Check the cameras, images and points3D files of ``model_dir`` (each .bin when present, else .txt)."""
    model_dir = Path(model_dir)

    def pick(name: str) -> Path:
        binary = model_dir / f"{name}.bin"
        return binary if binary.is_file() else model_dir / f"{name}.txt"

    cameras, images, points = pick("cameras"), pick("images"), pick("points3D")
    camera_ids = (check_cameras_bin if cameras.suffix == ".bin" else check_cameras_txt)(cameras, supported)
    if images.suffix == ".bin":
        image_ids = check_images_bin(images, camera_ids)
    else:  # 2D points may name 3D points a model no longer holds (an emptied points3D: random initial Gaussians)
        image_ids = check_images_txt(images, camera_ids, None)
    if points.is_file():
        if points.suffix == ".bin":
            check_points3d_bin(points, image_ids)
        else:
            check_points3d_txt(points, image_ids)


def import_pycolmap() -> ModuleType:
    """``import pycolmap``, keeping the SIGTERM handler Python had: pycolmap's import installs glog's failure handler
    over it, which prints a stack dump and kills the process, so that ``kill`` would end a tool without its one line
    (and a training without its checkpoint). An ImportError propagates, as the import's."""
    handler = signal.getsignal(signal.SIGTERM) if threading.current_thread() is threading.main_thread() else None
    import pycolmap

    if handler is not None:
        signal.signal(signal.SIGTERM, handler)  # the C-level handler back to Python's (or the default) one
    return pycolmap
