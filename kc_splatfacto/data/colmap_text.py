"""A COLMAP text model (``cameras.txt``, ``images.txt``, ``points3D.txt``) read without pycolmap.

pycolmap is the reader (:func:`kc_splatfacto.data.colmap.read_colmap_model`); this one serves where pycolmap cannot
be installed: a GPU image whose package budget leaves it out (pycolmap's wheel is 38 MB; the GPU campaign
carries at most 64 MiB per call). It returns the few attributes of ``pycolmap.Reconstruction`` that
``read_colmap_model`` uses, and fails where pycolmap's text reader fails (a non-finite pose or point), so both paths
go through the same checks and messages. Cameras, poses and points are the same as pycolmap's; the points come in
the file's order, pycolmap's in its hash map's (the seed Gaussians' order, so a run from either reader starts from the
same Gaussians in another order: not bit for bit the same run). The files are checked line by line first
(:func:`kc_splatfacto.data.colmap_files.check_model_files`), so parsing here assumes well-formed lines.
Tested against pycolmap on every shared scene (``tests/data/test_colmap_text.py``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kc_splatfacto.data.colmap_files import _data_lines


@dataclass(frozen=True)
class TextCamera:
    """pycolmap.Camera's fields as read_colmap_model uses them: ``model`` is the model's name."""

    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class TextRotation:
    quat: np.ndarray  # [4] x, y, z, w (pycolmap's order), as written: not normalized


@dataclass(frozen=True)
class TextRigid:
    """cam_from_world: a rotation and a translation [3]."""

    rotation: TextRotation
    translation: np.ndarray

    def matrix(self) -> np.ndarray:
        """[3, 4] world-to-camera [R | t], R of the quaternion as written (Eigen's formula, as pycolmap: no
        normalization, so a zero quaternion gives a finite matrix and the caller's norm check names it)."""
        return np.concatenate([quaternion_rotation(self.rotation.quat), self.translation[:, None]], axis=1)


def quaternion_rotation(quat_xyzw: np.ndarray) -> np.ndarray:
    """[3, 3] rotation matrix of a quaternion [4] in pycolmap's x, y, z, w order, as given (normalize it first)."""
    x, y, z, w = quat_xyzw
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


@dataclass(frozen=True)
class TextImage:
    image_id: int
    name: str
    camera_id: int
    cam_from_world: TextRigid


@dataclass(frozen=True)
class TextPoint:
    xyz: np.ndarray  # [3] float64
    color: np.ndarray  # [3] uint8


@dataclass(frozen=True)
class TextReconstruction:
    """id -> camera, id -> image, id -> 3D point (a text model's contents)."""

    cameras: dict[int, TextCamera]
    images: dict[int, TextImage]
    points3D: dict[int, TextPoint]  # noqa: N815 (pycolmap's name)


def _content_lines(path: Path) -> list[str]:
    """Every line that is not a comment, stripped (empty lines kept: an image's 2D-points line may be empty)."""
    return [line for _, line in _data_lines(path) if not line.startswith("#")]


def read_cameras_txt(path: Path) -> dict[int, TextCamera]:
    cameras: dict[int, TextCamera] = {}
    for line in _content_lines(path):
        if line:
            fields = line.split()
            cameras[int(fields[0])] = TextCamera(fields[1], int(fields[2]), int(fields[3]),
                                                 tuple(float(v) for v in fields[4:]))
    return cameras


def read_images_txt(path: Path) -> dict[int, TextImage]:
    """Pose lines ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``, each followed by its 2D-points line (skipped)."""
    lines = _content_lines(path)
    images: dict[int, TextImage] = {}
    i = 0
    while i < len(lines):
        if not lines[i]:
            i += 1
            continue
        fields = lines[i].split()
        qw, qx, qy, qz, tx, ty, tz = (float(v) for v in fields[1:8])
        if not np.isfinite([qw, qx, qy, qz, tx, ty, tz]).all():  # pycolmap's text reader fails here too
            raise ValueError(f"{path}: image {fields[0]} has a non-finite pose")
        pose = TextRigid(TextRotation(np.array([qx, qy, qz, qw])), np.array([tx, ty, tz]))
        images[int(fields[0])] = TextImage(int(fields[0]), " ".join(fields[9:]), int(fields[8]), pose)
        i += 2
    return images


def read_points3d_txt(path: Path) -> dict[int, TextPoint]:
    """``POINT3D_ID X Y Z R G B ERROR TRACK[]``; an absent file is an empty model's points."""
    points: dict[int, TextPoint] = {}
    if not path.is_file():
        return points
    for line in _content_lines(path):
        if line:
            fields = line.split()
            xyz = [float(v) for v in fields[1:4]]
            if not np.isfinite(xyz).all():  # as pycolmap's reader: the caller reads again without these lines
                raise ValueError(f"{path}: point {fields[0]} has non-finite coordinates")
            points[int(fields[0])] = TextPoint(np.array(xyz),
                                               np.array([int(v) for v in fields[4:7]], np.uint8))
    return points


def read_text_model(model_dir: str | Path) -> TextReconstruction:
    """The text model in ``model_dir`` (checked beforehand by ``check_model_files``)."""
    model_dir = Path(model_dir)
    return TextReconstruction(read_cameras_txt(model_dir / "cameras.txt"), read_images_txt(model_dir / "images.txt"),
                              read_points3d_txt(model_dir / "points3D.txt"))
