"""Smooth camera paths through key cameras: slerp of the orientations, linear interpolation of the centres.

Interpolation happens in camera-to-world form (a rotation and a centre), which is what a viewer moves; the result is
turned back into world-to-camera ``viewmats`` (OpenCV axes) for the rasterizer. Computed in float64.
"""

from __future__ import annotations

import torch

from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.render.projection import quat_to_rotmat, rotmat_to_quat

#: Below this angle (radians) between two orientations slerp degenerates to lerp + renormalize.
SLERP_LINEAR_THRESHOLD = 1e-6


def slerp(q0: torch.Tensor, q1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Spherical linear interpolation of unit quaternions along the shorter arc.

    Args:
        q0, q1: [N,4] unit quaternions. t: [N] fractions in [0,1].
    Returns:
        [N,4] unit quaternions; t=0 gives q0, t=1 gives q1 (or -q1, the same rotation).
    """
    q0 = q0.to(torch.float64)
    q1 = q1.to(torch.float64)
    t = t.to(torch.float64).reshape(-1, 1)
    dot = (q0 * q1).sum(-1, keepdim=True)
    q1 = torch.where(dot < 0, -q1, q1)  # q and -q are the same rotation: take the short way round
    dot = dot.abs().clamp(max=1.0)
    theta = torch.arccos(dot)
    sin_theta = torch.sin(theta)
    linear = theta < SLERP_LINEAR_THRESHOLD
    safe_sin = torch.where(linear, torch.ones_like(sin_theta), sin_theta)
    w0 = torch.where(linear, 1 - t, torch.sin((1 - t) * theta) / safe_sin)
    w1 = torch.where(linear, t, torch.sin(t * theta) / safe_sin)
    q = w0 * q0 + w1 * q1
    return q / q.norm(dim=-1, keepdim=True)


def interpolate_camera_path(keyframes: Cameras, num_frames: int, loop: bool = False) -> Cameras:
    """A path of ``num_frames`` cameras through the key cameras, in their given order, at uniform parameter steps.

    Orientations are slerped and centres and intrinsics interpolated linearly between consecutive keys; the first
    frame is the first key, and the last frame is the last key (or, with ``loop``, the frame before returning to the
    first key). All keys must share one image size.

    Args:
        keyframes: K >= 1 cameras (viewmats [K,4,4] world-to-camera OpenCV, Ks [K,3,3]).
        num_frames: number of output cameras (>= 1).
    Returns:
        Cameras of length ``num_frames`` (float32 matrices, the keys' width and height).
    """
    k = len(keyframes)
    if k == 0:
        raise ValueError("interpolate_camera_path: no key cameras given (the split is empty)")
    if num_frames < 1:
        raise ValueError(f"interpolate_camera_path: num_frames must be >= 1, got {num_frames}")
    if not (bool((keyframes.widths == keyframes.widths[0]).all()) and bool((keyframes.heights == keyframes.heights[0]).all())):
        raise ValueError("interpolate_camera_path: key cameras have different image sizes; a video needs one size")
    c2w = torch.linalg.inv(keyframes.viewmats.to(torch.float64))
    quats = rotmat_to_quat(c2w[:, :3, :3])
    centres = c2w[:, :3, 3]
    Ks = keyframes.Ks.to(torch.float64)
    if loop and k > 1:
        quats = torch.cat([quats, quats[:1]])
        centres = torch.cat([centres, centres[:1]])
        Ks = torch.cat([Ks, Ks[:1]])
    segments = quats.shape[0] - 1
    if segments == 0:
        s = torch.zeros(num_frames, dtype=torch.float64)
    elif loop:
        s = torch.arange(num_frames, dtype=torch.float64) * (segments / num_frames)
    else:
        s = torch.linspace(0, segments, num_frames, dtype=torch.float64)
    index = s.floor().long().clamp(max=max(segments - 1, 0))
    t = s - index.to(torch.float64)
    upper = (index + 1).clamp(max=quats.shape[0] - 1)
    q = slerp(quats[index], quats[upper], t)
    centre = (1 - t)[:, None] * centres[index] + t[:, None] * centres[upper]
    K = (1 - t)[:, None, None] * Ks[index] + t[:, None, None] * Ks[upper]
    c2w_path = torch.eye(4, dtype=torch.float64).repeat(num_frames, 1, 1)
    c2w_path[:, :3, :3] = quat_to_rotmat(q)
    c2w_path[:, :3, 3] = centre
    viewmats = torch.linalg.inv(c2w_path)
    return Cameras(
        viewmats=viewmats.to(torch.float32),
        Ks=K.to(torch.float32),
        widths=keyframes.widths[:1].repeat(num_frames),
        heights=keyframes.heights[:1].repeat(num_frames),
    )
