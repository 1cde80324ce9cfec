"""Tiny synthetic scenes (48x32 images, 6 cameras around a point cloud) in every format the parsers read, for the
hostile-input suite: a case edits one file of a fresh copy and runs a command on it."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

WIDTH, HEIGHT = 48, 32
NUM_VIEWS = 6
FOCAL = 40.0


def look_at_c2w(position: np.ndarray) -> np.ndarray:
    """[4,4] OpenCV camera-to-world (x right, y down, z forward) at ``position`` looking at the origin, z up."""
    forward = -position / np.linalg.norm(position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, down, forward], axis=1)
    c2w[:3, 3] = position
    return c2w


def camera_poses() -> list[np.ndarray]:
    angles = np.linspace(0.0, 2.0 * np.pi, NUM_VIEWS, endpoint=False)
    return [look_at_c2w(np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 1.0])) for a in angles]


def quaternion_wxyz(rotation: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a proper rotation (Shepperd's method, w >= 0 branch is enough here)."""
    w = np.sqrt(max(0.0, 1.0 + np.trace(rotation))) / 2.0
    if w > 1e-6:
        x = (rotation[2, 1] - rotation[1, 2]) / (4 * w)
        y = (rotation[0, 2] - rotation[2, 0]) / (4 * w)
        z = (rotation[1, 0] - rotation[0, 1]) / (4 * w)
        return np.array([w, x, y, z])
    i = int(np.argmax(np.diag(rotation)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = np.sqrt(1.0 + rotation[i, i] - rotation[j, j] - rotation[k, k]) * 2.0
    q = np.zeros(4)
    q[0] = (rotation[k, j] - rotation[j, k]) / s
    q[1 + i] = s / 4.0
    q[1 + j] = (rotation[j, i] + rotation[i, j]) / s
    q[1 + k] = (rotation[k, i] + rotation[i, k]) / s
    return q


def write_images(folder: Path, suffix: str = ".png") -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    names = []
    for i in range(NUM_VIEWS):
        yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
        image = np.stack([xx * 5 + 20 * i, yy * 7, (xx + yy) * 3], axis=-1) % 256
        image = (image + rng.integers(0, 20, image.shape)).clip(0, 255).astype(np.uint8)
        name = f"{i:04d}{suffix}"
        cv2.imwrite(str(folder / name), image)
        names.append(name)
    return names


def seed_points(n: int = 200) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(1)
    return rng.uniform(-0.5, 0.5, (n, 3)), rng.integers(0, 256, (n, 3))


def transforms_scene(root: Path) -> Path:
    """A nerfstudio transforms.json scene (OpenGL camera-to-world, global PINHOLE intrinsics)."""
    names = write_images(root / "images")
    frames = []
    for name, c2w in zip(names, camera_poses()):
        gl = c2w.copy()
        gl[:3, 1:3] *= -1.0
        frames.append({"file_path": f"images/{name}", "transform_matrix": gl.tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": FOCAL, "fl_y": FOCAL, "cx": WIDTH / 2, "cy": HEIGHT / 2,
            "w": WIDTH, "h": HEIGHT, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(meta, indent=1))
    return root


def colmap_scene(root: Path, binary: bool = False) -> Path:
    """A COLMAP scene: images/ and sparse/0 with cameras, images and points3D as text (or binary, via pycolmap)."""
    names = write_images(root / "images")
    model = root / "sparse" / "0"
    model.mkdir(parents=True)
    (model / "cameras.txt").write_text(
        f"# Camera list\n1 PINHOLE {WIDTH} {HEIGHT} {FOCAL} {FOCAL} {WIDTH / 2} {HEIGHT / 2}\n"
    )
    xyz, rgb = seed_points()
    lines = ["# Image list"]
    for image_id, (name, c2w) in enumerate(zip(names, camera_poses()), start=1):
        w2c = np.linalg.inv(c2w)
        q = quaternion_wxyz(w2c[:3, :3])
        t = w2c[:3, 3]
        lines.append(" ".join(str(v) for v in [image_id, *q.tolist(), *t.tolist(), 1, name]))
        lines.append(f"10.0 10.0 {image_id}")  # observes point image_id (tracks below list it back)
    (model / "images.txt").write_text("\n".join(lines) + "\n")
    points = ["# 3D point list"]
    for point_id, (p, c) in enumerate(zip(xyz, rgb), start=1):
        track = f" {point_id} 0" if point_id <= NUM_VIEWS else ""
        points.append(f"{point_id} {p[0]} {p[1]} {p[2]} {c[0]} {c[1]} {c[2]} 0.5{track}")
    (model / "points3D.txt").write_text("\n".join(points) + "\n")
    if binary:  # written by pycolmap: a test of a binary model skips where it is absent (the GPU campaign's image)
        pycolmap = pytest.importorskip("pycolmap")

        reconstruction = pycolmap.Reconstruction(str(model))
        for name in ("cameras", "images", "points3D"):
            (model / f"{name}.txt").unlink()
        reconstruction.write_binary(str(model))
        for extra in model.iterdir():  # pycolmap 3.12 also writes rigs.bin / frames.bin
            if extra.stem not in ("cameras", "images", "points3D"):
                extra.unlink()
    return root


def tree_digest(folder: Path, exclude: Path | None = None) -> dict[str, str]:
    """Every file under ``folder`` (but ``exclude``) with a hash of its bytes and its mode."""
    out = {}
    for path in sorted(Path(folder).rglob("*")):
        if exclude is not None and (path == exclude or exclude in path.parents):
            continue
        if path.is_file() and not path.is_symlink():
            out[str(path)] = hashlib.sha1(path.read_bytes()).hexdigest() + f" {path.stat().st_mode:o}"
        elif path.is_dir():
            out[str(path)] = "dir"
    return out
