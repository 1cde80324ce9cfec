"""Camera path interpolation: endpoints hit the keys, rotations follow the geodesic (scipy oracle), centres lerp."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation, Slerp

from kc_splatfacto.analysis.camera_path import interpolate_camera_path
from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.render import quat_to_rotmat
from kc_splatfacto.render.projection import rotmat_to_quat


def _keys(num: int = 4, seed: int = 0) -> tuple[Cameras, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rots = Rotation.random(num, random_state=seed)
    centres = rng.normal(size=(num, 3))
    c2w = np.tile(np.eye(4), (num, 1, 1))
    c2w[:, :3, :3] = rots.as_matrix()
    c2w[:, :3, 3] = centres
    K = np.array([[100.0, 0, 32], [0, 100.0, 24], [0, 0, 1]])
    cams = Cameras(
        viewmats=torch.tensor(np.linalg.inv(c2w), dtype=torch.float32),
        Ks=torch.tensor(np.tile(K, (num, 1, 1)), dtype=torch.float32),
        widths=torch.full((num,), 64), heights=torch.full((num,), 48),
    )
    return cams, rots.as_matrix(), centres


def test_quaternion_conversions_match_scipy():
    rots = Rotation.random(100, random_state=1)
    q = rotmat_to_quat(torch.tensor(rots.as_matrix()))
    ref = rots.as_quat()[:, [3, 0, 1, 2]]  # scipy is xyzw
    ref = np.where(ref[:, :1] < 0, -ref, ref)
    np.testing.assert_allclose(q.numpy(), ref, atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(q).numpy(), rots.as_matrix(), atol=1e-12)


def test_path_through_keys():
    cams, rots, centres = _keys(4)
    per_segment = 5
    path = interpolate_camera_path(cams, num_frames=3 * per_segment + 1)
    assert len(path) == 16 and path.widths.tolist() == [64] * 16
    c2w = np.linalg.inv(path.viewmats.double().numpy())
    for key in range(4):
        frame = key * per_segment
        np.testing.assert_allclose(c2w[frame, :3, :3], rots[key], atol=1e-5)
        np.testing.assert_allclose(c2w[frame, :3, 3], centres[key], atol=1e-5)
    # Between keys: the scipy slerp of the two key rotations, and the linear blend of centres.
    for frame in (1, 7, 13):
        seg, t = divmod(frame, per_segment)
        t /= per_segment
        ref_rot = Slerp([0, 1], Rotation.from_matrix(rots[seg:seg + 2]))([t]).as_matrix()[0]
        np.testing.assert_allclose(c2w[frame, :3, :3], ref_rot, atol=1e-5)
        np.testing.assert_allclose(c2w[frame, :3, 3], (1 - t) * centres[seg] + t * centres[seg + 1], atol=1e-5)


def test_loop_and_single_key():
    cams, rots, centres = _keys(3)
    path = interpolate_camera_path(cams, num_frames=6, loop=True)
    c2w = np.linalg.inv(path.viewmats.double().numpy())
    np.testing.assert_allclose(c2w[4, :3, 3], centres[2], atol=1e-5)
    np.testing.assert_allclose(c2w[5, :3, 3], 0.5 * (centres[2] + centres[0]), atol=1e-5)
    single = interpolate_camera_path(cams[0], num_frames=3)
    torch.testing.assert_close(single.viewmats, cams.viewmats[:1].repeat(3, 1, 1), atol=1e-5, rtol=0)


def test_bad_inputs():
    cams, _, _ = _keys(2)
    with pytest.raises(ValueError, match="no key cameras"):
        interpolate_camera_path(cams[0:0], 5)
    with pytest.raises(ValueError, match="num_frames"):
        interpolate_camera_path(cams, 0)
    cams.widths[1] = 32
    with pytest.raises(ValueError, match="image sizes"):
        interpolate_camera_path(cams, 5)
