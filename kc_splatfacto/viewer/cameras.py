"""Between the browser's camera and the project's: pure functions, no server.

viser's camera is a camera-to-world pose in OpenCV axes (``wxyz`` rotation, ``position``), a vertical field of view
in radians and the canvas size in pixels; the project's :class:`~kc_splatfacto.data.outputs.Cameras` are
world-to-camera ``viewmats`` in the same axes and pinhole ``Ks``. Both live in the run's normalized world, so no
scale or axis change is needed between them. nerfstudio's camera-path JSON holds OpenGL-axes camera-to-world
matrices (x right, y up, z back) and vertical fields of view in degrees.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from kc_splatfacto.analysis.camera_path import camera_entries, camera_path_dict, interpolate_camera_path
from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.render.constants import SH_C0
from kc_splatfacto.render.projection import quat_to_rotmat, rotmat_to_quat

#: a training frustum's size (viser's ``scale``: its depth, in world units) as a fraction of the median distance from
#: a camera centre to its nearest neighbour's: the initial view is a test camera among the training ones, and at a
#: tenth the thumbnails of its neighbours cover under 2 % of it on the project's LLFF, Strecha and demo scenes (up to
#: half of it with 0.05 x the cameras' extent, the earlier rule, on 100 cameras along a path), while frustums of
#: sparse captures keep about their earlier size
FRUSTUM_SPACING_FRACTION = 0.1
#: the size when there is no spacing to go by (one camera, or all at one place): the dataparsers scale the world so
#: that the cameras lie within about a unit of its centre
FRUSTUM_FALLBACK_SCALE = 0.1


def frustum_scale(centres: np.ndarray) -> float:
    """The size of the training cameras' frustums for camera centres ``centres`` [N, 3]: ``FRUSTUM_SPACING_FRACTION``
    x the median nearest-neighbour distance between the distinct centres (cameras at one place count once), or
    ``FRUSTUM_FALLBACK_SCALE`` with fewer than two distinct centres."""
    from scipy.spatial import cKDTree

    distinct = np.unique(np.asarray(centres, dtype=np.float64).reshape(-1, 3), axis=0)
    if len(distinct) < 2:
        return FRUSTUM_FALLBACK_SCALE
    nearest, _ = cKDTree(distinct).query(distinct, k=2)  # the first neighbour is the centre itself
    return FRUSTUM_SPACING_FRACTION * float(np.median(nearest[:, 1]))


def render_size(width: int, height: int, max_pixels: int) -> tuple[int, int]:
    """The canvas size ``width`` x ``height`` scaled down (aspect kept, at least 1x1) to at most ``max_pixels``."""
    width, height = max(int(width), 1), max(int(height), 1)
    scale = min(1.0, math.sqrt(max_pixels / (width * height)))
    return max(int(width * scale), 1), max(int(height * scale), 1)


def pinhole_K(fov_y: float, width: int, height: int) -> torch.Tensor:
    """[3, 3] intrinsics of a centred pinhole with square pixels and vertical field of view ``fov_y`` (radians)."""
    focal = 0.5 * height / math.tan(0.5 * fov_y)
    return torch.tensor([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]], dtype=torch.float32)


def camera_from_pose(wxyz: Any, position: Any, fov_y: float, width: int, height: int) -> Cameras:
    """One camera (batch of 1) from a viser pose: ``wxyz`` [4] camera-to-world rotation, ``position`` [3]."""
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz, dtype=np.float64))[None])[0]
    c2w[:3, 3] = torch.as_tensor(np.asarray(position, dtype=np.float64))
    return Cameras(viewmats=torch.linalg.inv(c2w)[None].to(torch.float32), Ks=pinhole_K(fov_y, width, height)[None],
                   widths=torch.tensor([width]), heights=torch.tensor([height]))


def pose_of(cameras: Cameras) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wxyz [N, 4], position [N, 3], vertical fov [N] in radians) of ``cameras``: what viser's camera and frustum
    handles take."""
    c2w = torch.linalg.inv(cameras.viewmats.to(torch.float64))
    wxyz = rotmat_to_quat(c2w[:, :3, :3]).numpy()
    fov = 2.0 * np.arctan(0.5 * cameras.heights.double().numpy() / cameras.Ks[:, 1, 1].double().numpy())
    return wxyz, c2w[:, :3, 3].numpy(), fov


def world_up(cameras: Cameras) -> np.ndarray:
    """[3] unit vector: the mean 'up' of the cameras (OpenCV's -y axis), the orbit controls' up direction."""
    c2w = torch.linalg.inv(cameras.viewmats.to(torch.float64))
    up = -c2w[:, :3, 1].mean(dim=0).numpy()
    norm = np.linalg.norm(up)
    return up / norm if norm > 0 else np.array([0.0, 0.0, 1.0])


def splat_arrays(model) -> dict[str, np.ndarray]:
    """What the PLY export holds, as viser's ``add_gaussian_splats`` takes it: ``centers`` [N, 3], ``covariances``
    [N, 3, 3] (R diag(s^2) R^T), ``rgbs`` [N, 3] (the view-independent colour), ``opacities`` [N, 1]."""
    with torch.no_grad():
        rotations = quat_to_rotmat(model.quats.detach().double())
        scales = torch.exp(model.scales.detach().double())
        covariances = rotations @ torch.diag_embed(scales**2) @ rotations.transpose(-1, -2)
        dc = model.features_dc.detach().double()
        rgbs = (SH_C0 * dc + 0.5) if model.sh_degree > 0 else torch.sigmoid(dc)
        return {
            "centers": model.means.detach().cpu().numpy().astype(np.float32),
            "covariances": covariances.cpu().numpy().astype(np.float32),
            "rgbs": rgbs.clamp(0, 1).cpu().numpy().astype(np.float32),
            "opacities": torch.sigmoid(model.opacities.detach()).reshape(-1, 1).cpu().numpy().astype(np.float32),
        }


def camera_path_json(keyframes: Cameras, fps: float, seconds: float, loop: bool = False) -> dict[str, Any]:
    """nerfstudio's camera-path JSON (its viewer's export, ``ns-render camera-path``'s input) through ``keyframes``:
    ``camera_path`` holds ``round(fps * seconds)`` cameras interpolated through the keys (slerped orientations,
    lerped centres and intrinsics) as :func:`~kc_splatfacto.analysis.camera_path.camera_path_dict` writes them, and
    nerfstudio's viewer fields beside: ``keyframes`` (the keys, ``matrix`` in the same form), ``seconds`` as asked,
    ``is_cycle``."""
    if len(keyframes) == 0:
        raise ValueError("camera_path_json: no keyframes")
    num_frames = max(int(round(fps * seconds)), 1)
    data = camera_path_dict(interpolate_camera_path(keyframes, num_frames, loop=loop), fps)
    data.update(seconds=float(seconds), is_cycle=bool(loop), keyframes=camera_entries(keyframes, "matrix"))
    return data
