"""Camera paths for videos: nerfstudio's camera-path JSON (the viewer's export, ``ns-render camera-path``'s input),
a path through key cameras (scipy's Slerp of the orientations, linear centres), and an LLFF-style spiral.

Interpolation happens in camera-to-world form (a rotation and a centre), which is what a viewer moves; the result is
turned back into world-to-camera ``viewmats`` (OpenCV axes) for the rasterizer. Computed in float64.

The JSON (nerfstudio's ``get_path_from_json``)::

    {"camera_type": "perspective", "render_width": W, "render_height": H, "fps": 24, "seconds": 5,
     "camera_path": [{"camera_to_world": [16 numbers, row-major 4x4, OpenGL axes: x right, y up, z back],
                      "fov": vertical field of view in degrees, "aspect": W / H}, ...]}

in the world the model lives in (the dataparser's normalized one, as nerfstudio's). Each camera becomes a pinhole
with ``fx = fy = (H / 2) / tan(fov / 2)`` and the principal point at the image centre ``(W / 2, H / 2)``; the frame
rate is ``fps``, else ``len(camera_path) / seconds``, else the caller's.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.errors import UserError

#: OpenGL camera axes (nerfstudio, three.js: y up, looking down -z) from OpenCV's (y down, looking down +z)
GL_FROM_CV = np.diag([1.0, -1.0, -1.0])
#: the only camera type of nerfstudio's JSON a pinhole rasterizer renders
PERSPECTIVE = "perspective"
#: spiral: turns around the mean camera, vertical oscillation per turn, and the percentile of the cameras' offsets
#: from their mean that sets the radius (LLFF's render_path_spiral and nerfstudio's get_spiral_path)
SPIRAL_ROTATIONS = 2
SPIRAL_ZRATE = 0.5
SPIRAL_RADIUS_PERCENTILE = 90
#: the narrowest angle a pixel may span (radians): float32's relative resolution, since the rasterizer projects in
#: float32; below it a projected point's rounding error is more than a pixel, and a fov small enough makes the focal
#: length itself infinite (a traceback from the rasterizer, or a division by zero)
MIN_PIXEL_ANGLE = float(np.finfo(np.float32).eps)


class CameraPathError(UserError, ValueError):
    """A camera-path JSON that cannot be rendered: the message names the file, the field and the fix."""


@dataclass
class CameraPath:
    """Cameras along a path and the frame rate to play them at (None: the file did not say)."""

    cameras: Cameras
    fps: float | None


def _cameras(c2w_cv: np.ndarray, Ks: np.ndarray, width: int, height: int) -> Cameras:
    n = c2w_cv.shape[0]
    return Cameras(
        viewmats=torch.tensor(np.linalg.inv(c2w_cv), dtype=torch.float32),
        Ks=torch.tensor(Ks, dtype=torch.float32),
        widths=torch.full((n,), int(width), dtype=torch.int64),
        heights=torch.full((n,), int(height), dtype=torch.int64),
    )


def interpolate_camera_path(keyframes: Cameras, num_frames: int, loop: bool = False) -> Cameras:
    """A path of ``num_frames`` cameras through the key cameras, in their given order, at uniform parameter steps.

    Orientations are slerped (``scipy.spatial.transform.Slerp``) and centres and intrinsics interpolated linearly
    between consecutive keys; the first frame is the first key, and the last frame is the last key (or, with
    ``loop``, the frame before returning to the first key). All keys must share one image size.

    Args:
        keyframes: K >= 1 cameras (viewmats [K,4,4] world-to-camera OpenCV, Ks [K,3,3]).
        num_frames: number of output cameras (>= 1).
    Returns:
        Cameras of length ``num_frames`` (float32 matrices, the keys' width and height).
    """
    from scipy.spatial.transform import Rotation, Slerp

    k = len(keyframes)
    if k == 0:
        raise ValueError("interpolate_camera_path: no key cameras given (the split is empty)")
    if num_frames < 1:
        raise ValueError(f"interpolate_camera_path: num_frames must be >= 1, got {num_frames}")
    if not (bool((keyframes.widths == keyframes.widths[0]).all()) and bool((keyframes.heights == keyframes.heights[0]).all())):
        raise ValueError("interpolate_camera_path: key cameras have different image sizes; a video needs one size")
    c2w = np.linalg.inv(keyframes.viewmats.double().numpy())
    rotations, centres, Ks = c2w[:, :3, :3], c2w[:, :3, 3], keyframes.Ks.double().numpy()
    if loop and k > 1:
        rotations, centres, Ks = (np.concatenate([a, a[:1]]) for a in (rotations, centres, Ks))
    segments = rotations.shape[0] - 1
    if segments == 0:
        s = np.zeros(num_frames)
    elif loop:
        s = np.arange(num_frames) * (segments / num_frames)
    else:
        s = np.linspace(0, segments, num_frames)
    index = np.minimum(np.floor(s).astype(int), max(segments - 1, 0))
    t = s - index
    upper = np.minimum(index + 1, rotations.shape[0] - 1)
    if segments == 0:
        path_rotations = np.repeat(rotations, num_frames, axis=0)
    else:
        path_rotations = Slerp(np.arange(segments + 1), Rotation.from_matrix(rotations))(s).as_matrix()
    c2w_path = np.tile(np.eye(4), (num_frames, 1, 1))
    c2w_path[:, :3, :3] = path_rotations
    c2w_path[:, :3, 3] = (1 - t)[:, None] * centres[index] + t[:, None] * centres[upper]
    K = (1 - t)[:, None, None] * Ks[index] + t[:, None, None] * Ks[upper]
    return _cameras(c2w_path, K, int(keyframes.widths[0]), int(keyframes.heights[0]))


def mean_camera(c2w: np.ndarray) -> np.ndarray:
    """[4,4] the average of camera-to-world poses [N,4,4]: mean centre, the rotation closest to the mean rotation."""
    from scipy.spatial.transform import Rotation

    out = np.eye(4)
    out[:3, :3] = Rotation.from_matrix(c2w[:, :3, :3]).mean().as_matrix()
    out[:3, 3] = c2w[:, :3, 3].mean(axis=0)
    return out


def spiral_camera_path(keyframes: Cameras, focus_points: np.ndarray, num_frames: int,
                       rotations: int = SPIRAL_ROTATIONS, zrate: float = SPIRAL_ZRATE) -> Cameras:
    """LLFF's spiral: ``num_frames`` cameras circling the mean key camera in its image plane (radius: the 90th
    percentile of the keys' offsets from it along its right and up axes), every one looking at the focus point.

    Args:
        keyframes: K >= 1 cameras of one image size (the first's intrinsics are used).
        focus_points: [M,3] world points (e.g. the Gaussians' centres); the focus is at their median depth in front
            of the mean camera (the mean keys' depth of 1 when none is in front).
        num_frames: >= 1.
    Returns:
        Cameras of length ``num_frames``.
    """
    if len(keyframes) == 0:
        raise ValueError("spiral_camera_path: no key cameras given (the split is empty)")
    if num_frames < 1:
        raise ValueError(f"spiral_camera_path: num_frames must be >= 1, got {num_frames}")
    c2w = np.linalg.inv(keyframes.viewmats.double().numpy())
    centre = mean_camera(c2w)
    rotation, origin = centre[:3, :3], centre[:3, 3]
    local = (c2w[:, :3, 3] - origin) @ rotation  # key centres in the mean camera's (right, down, forward) axes
    radius = np.percentile(np.abs(local), SPIRAL_RADIUS_PERCENTILE, axis=0)
    points = np.asarray(focus_points, dtype=np.float64).reshape(-1, 3)
    depths = (points - origin) @ rotation[:, 2]
    depths = depths[depths > 0]
    focus_depth = float(np.median(depths)) if depths.size else 1.0
    focus = origin + focus_depth * rotation[:, 2]
    theta = np.linspace(0.0, 2.0 * np.pi * rotations, num_frames + 1)[:-1]
    offsets = np.stack([np.cos(theta), -np.sin(theta), -np.sin(theta * zrate)], axis=1) * radius
    positions = origin + offsets @ rotation.T
    c2w_path = np.tile(np.eye(4), (num_frames, 1, 1))
    for i, position in enumerate(positions):
        forward = focus - position
        forward /= np.linalg.norm(forward)
        right = np.cross(rotation[:, 1], forward)  # OpenCV axes: down x forward = right
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        c2w_path[i, :3, :3] = np.stack([right, down, forward], axis=1)
        c2w_path[i, :3, 3] = position
    K = np.repeat(keyframes.Ks[:1].double().numpy(), num_frames, axis=0)
    return _cameras(c2w_path, K, int(keyframes.widths[0]), int(keyframes.heights[0]))


def _field(mapping: dict, key: str, where: str, path: Path):
    if not isinstance(mapping, dict) or key not in mapping:
        raise CameraPathError(f"camera path {path}: {where} has no '{key}' (nerfstudio's camera-path format: "
                              "render_width, render_height, camera_path[{camera_to_world, fov}])")
    return mapping[key]


def _number(value, what: str, path: Path, positive: bool = True) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or (
            positive and value <= 0):
        raise CameraPathError(f"camera path {path}: {what} must be a {'positive ' if positive else ''}number, "
                              f"got {value!r}")
    return float(value)


def check_fov_renders(fov: float, height: float, what: str, path: Path) -> None:
    """A :class:`CameraPathError` when a vertical field of view of ``fov`` degrees over ``height`` pixels gives
    pixels narrower than :data:`MIN_PIXEL_ANGLE`."""
    smallest = math.degrees(MIN_PIXEL_ANGLE * height)
    if fov < smallest:
        raise CameraPathError(
            f"camera path {path}: {what} is {fov:g} degrees, too narrow to render {height:g} pixels high (a pixel would "
            f"span {math.radians(fov) / height:.2g} rad, below the {MIN_PIXEL_ANGLE:.2g} rad float32 resolves): use a "
            f"fov of at least {smallest:.2g} degrees"
        )


def read_camera_path(path: Path) -> CameraPath:
    """Cameras of a nerfstudio camera-path JSON (the module docstring's format and conversion)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CameraPathError(f"camera path {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CameraPathError(f"camera path {path} is not readable JSON ({exc})") from None
    camera_type = data.get("camera_type", PERSPECTIVE) if isinstance(data, dict) else PERSPECTIVE
    if camera_type != PERSPECTIVE:
        raise CameraPathError(f"camera path {path}: camera_type '{camera_type}' is not rendered here: only "
                              f"'{PERSPECTIVE}' (the rasterizer draws pinhole cameras)")
    width = _number(_field(data, "render_width", "the file", path), "render_width", path)
    height = _number(_field(data, "render_height", "the file", path), "render_height", path)
    if width != int(width) or height != int(height):
        raise CameraPathError(f"camera path {path}: render_width and render_height must be whole pixels, got "
                              f"{width} x {height}")
    cameras = _field(data, "camera_path", "the file", path)
    if not isinstance(cameras, list) or not cameras:
        raise CameraPathError(f"camera path {path}: camera_path must be a non-empty list of cameras")
    c2w = np.tile(np.eye(4), (len(cameras), 1, 1))
    Ks = np.tile(np.eye(3), (len(cameras), 1, 1))
    for i, camera in enumerate(cameras):
        matrix = _field(camera, "camera_to_world", f"camera_path[{i}]", path)
        try:
            matrix = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
        except (TypeError, ValueError):
            raise CameraPathError(f"camera path {path}: camera_path[{i}].camera_to_world must be 16 numbers "
                                  "(a row-major 4x4 matrix)") from None
        rotation = matrix[:3, :3]
        if not np.isfinite(matrix).all() or not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-4) or \
                np.linalg.det(rotation) < 0:
            raise CameraPathError(f"camera path {path}: camera_path[{i}].camera_to_world is not a rigid pose "
                                  "(its 3x3 part must be a rotation)")
        fov = _number(_field(camera, "fov", f"camera_path[{i}]", path), f"camera_path[{i}].fov", path)
        if fov >= 180:
            raise CameraPathError(f"camera path {path}: camera_path[{i}].fov is {fov} degrees: a perspective "
                                  "camera's vertical field of view is below 180")
        check_fov_renders(fov, height, f"camera_path[{i}].fov", path)
        c2w[i, :3, :3] = rotation @ GL_FROM_CV
        c2w[i, :3, 3] = matrix[:3, 3]
        focal = (height / 2.0) / math.tan(math.radians(fov) / 2.0)
        Ks[i] = [[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]]
    fps = data.get("fps")
    if fps is not None:
        fps = _number(fps, "fps", path)
    elif data.get("seconds") is not None:
        fps = len(cameras) / _number(data["seconds"], "seconds", path)
    return CameraPath(_cameras(c2w, Ks, int(width), int(height)), fps)


def camera_entries(cameras: Cameras, matrix_key: str = "camera_to_world") -> list[dict]:
    """nerfstudio's per-camera entries of ``cameras`` (one image size): ``matrix_key`` (``camera_to_world`` in a path,
    ``matrix`` in its viewer's keyframes) the OpenGL-axes camera-to-world as 16 row-major numbers, ``fov`` the
    vertical field of view from ``fy`` in degrees, ``aspect`` W / H. The principal point is not kept: the format puts
    it at the image centre."""
    width, height = int(cameras.widths[0]), int(cameras.heights[0])
    c2w = np.linalg.inv(cameras.viewmats.double().numpy())
    entries = []
    for i in range(len(cameras)):
        matrix = np.eye(4)
        matrix[:3, :3] = c2w[i, :3, :3] @ GL_FROM_CV
        matrix[:3, 3] = c2w[i, :3, 3]
        fov = math.degrees(2.0 * math.atan((height / 2.0) / float(cameras.Ks[i, 1, 1])))
        entries.append({matrix_key: matrix.reshape(-1).tolist(), "fov": fov, "aspect": width / height})
    return entries


def camera_path_dict(cameras: Cameras, fps: float) -> dict:
    """nerfstudio's camera-path JSON of ``cameras`` (one image size), played at ``fps``."""
    return {"camera_type": PERSPECTIVE, "render_width": int(cameras.widths[0]),
            "render_height": int(cameras.heights[0]), "fps": float(fps), "seconds": len(cameras) / fps,
            "camera_path": camera_entries(cameras)}
