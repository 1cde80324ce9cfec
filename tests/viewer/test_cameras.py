"""kc_splatfacto/viewer/cameras.py: the browser's camera <-> the project's, PLY-equivalent splats, camera-path JSON."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from kc_splatfacto.data.demo import DemoDataParserConfig
from kc_splatfacto.viewer.cameras import (
    FRUSTUM_FALLBACK_SCALE,
    FRUSTUM_SPACING_FRACTION,
    camera_from_pose,
    camera_path_json,
    frustum_scale,
    pose_of,
    render_size,
    splat_arrays,
    world_up,
)


@pytest.fixture(scope="module")
def demo_cameras():
    parser = DemoDataParserConfig(width=64, height=48).setup()
    return parser.get_dataparser_outputs("train").cameras


def test_render_size_keeps_the_aspect_and_the_pixel_budget():
    width, height = render_size(800, 450, 160 * 120)
    assert width * height <= 160 * 120 and abs(width / height - 800 / 450) < 0.02
    assert render_size(100, 50, 10**6) == (100, 50)  # never upscaled
    assert render_size(0, 0, 100) == (1, 1)


def test_a_viser_pose_round_trips_to_the_same_camera(demo_cameras):
    """pose_of -> camera_from_pose gives back the camera (its viewmat, and K when the size is the camera's)."""
    for i in range(len(demo_cameras)):
        camera = demo_cameras[i]
        wxyz, position, fov = pose_of(camera)
        rebuilt = camera_from_pose(wxyz[0], position[0], float(fov[0]), int(camera.widths[0]), int(camera.heights[0]))
        torch.testing.assert_close(rebuilt.viewmats, camera.viewmats, atol=1e-5, rtol=0)
        # scipy's independent reading of the quaternion: the camera-to-world rotation (scipy is xyzw)
        c2w = torch.linalg.inv(camera.viewmats[0].double()).numpy()
        np.testing.assert_allclose(Rotation.from_quat(np.roll(wxyz[0], -1)).as_matrix(), c2w[:3, :3], atol=1e-6)
        assert math.isclose(rebuilt.Ks[0, 1, 1], camera.Ks[0, 1, 1], rel_tol=1e-5)


def test_world_up_is_the_cameras_minus_y_axis(demo_cameras):
    up = world_up(demo_cameras)
    c2w = torch.linalg.inv(demo_cameras.viewmats.double())
    assert float(np.dot(up, -c2w[0, :3, 1].numpy())) > 0.5 and math.isclose(np.linalg.norm(up), 1.0)


def test_camera_path_json_is_nerfstudios_format(demo_cameras):
    keys = demo_cameras[0:3]
    data = camera_path_json(keys, fps=10, seconds=2)
    assert data["camera_type"] == "perspective" and len(data["camera_path"]) == 20 and len(data["keyframes"]) == 3
    assert (data["render_width"], data["render_height"]) == (int(keys.widths[0]), int(keys.heights[0]))
    first = np.array(data["camera_path"][0]["camera_to_world"]).reshape(4, 4)
    last = np.array(data["camera_path"][-1]["camera_to_world"]).reshape(4, 4)
    for matrix, index in ((first, 0), (last, 2)):
        # OpenGL axes: x right, y up, z backwards, i.e. the OpenCV camera-to-world with y and z negated
        opencv = torch.linalg.inv(keys.viewmats[index].double()).numpy()
        np.testing.assert_allclose(matrix[:, 0], opencv[:, 0], atol=1e-5)
        np.testing.assert_allclose(matrix[:3, 1:3], -opencv[:3, 1:3], atol=1e-5)
        np.testing.assert_allclose(matrix[:3, 3], opencv[:3, 3], atol=1e-5)
    fov = math.degrees(2 * math.atan(0.5 * float(keys.heights[0]) / float(keys.Ks[0, 1, 1])))
    assert math.isclose(data["camera_path"][0]["fov"], fov, rel_tol=1e-5)
    assert data["keyframes"][1]["matrix"] == pytest.approx(
        (torch.linalg.inv(keys.viewmats[1].double()).numpy() @ np.diag([1, -1, -1, 1])).reshape(-1).tolist(), abs=1e-6)


def test_splats_are_what_the_ply_export_holds(tmp_path):
    """Centres, covariances, colours and opacities from kc-export's PLY, read back by trimesh and recomputed here
    with scipy's rotations, equal splat_arrays of the model."""
    from kc_splatfacto.model.gaussians_ply import export_ply
    from kc_splatfacto.model.splatfacto import SplatfactoModelConfig

    torch.manual_seed(0)
    model = SplatfactoModelConfig(random_init=True, num_random=50).setup(scene_scale=1.0)
    with torch.no_grad():
        model.scales.add_(torch.randn_like(model.scales) * 0.3)
        model.quats.copy_(torch.randn_like(model.quats))
    path = export_ply(tmp_path / "s.ply", model.gauss_params).path
    vertex = trimesh.load(path, process=False).metadata["_ply_raw"]["vertex"]["data"]
    splats = splat_arrays(model)
    np.testing.assert_allclose(splats["centers"], np.stack([vertex["x"], vertex["y"], vertex["z"]], 1), atol=1e-6)
    rot = Rotation.from_quat(np.stack([vertex["rot_1"], vertex["rot_2"], vertex["rot_3"], vertex["rot_0"]], 1)).as_matrix()
    s2 = np.exp(2 * np.stack([vertex["scale_0"], vertex["scale_1"], vertex["scale_2"]], 1).astype(np.float64))
    np.testing.assert_allclose(splats["covariances"], np.einsum("nij,nj,nkj->nik", rot, s2, rot), rtol=1e-4, atol=1e-7)
    dc = np.stack([vertex["f_dc_0"], vertex["f_dc_1"], vertex["f_dc_2"]], 1).astype(np.float64)
    np.testing.assert_allclose(splats["rgbs"], np.clip(0.28209479177387814 * dc + 0.5, 0, 1), atol=1e-6)
    np.testing.assert_allclose(splats["opacities"][:, 0], 1 / (1 + np.exp(-vertex["opacity"].astype(np.float64))), atol=1e-6)


# ----------------------------------------------------------------------------------- frustum size (issue 37, cat. 8)
def _median_nearest_brute_force(centres: np.ndarray) -> float:
    """The median over distinct centres of the distance to the nearest other one, from every pairwise distance."""
    distinct = np.array(sorted({tuple(c) for c in centres.tolist()}))
    distances = np.sqrt(((distinct[:, None, :] - distinct[None, :, :]) ** 2).sum(-1))
    np.fill_diagonal(distances, np.inf)
    return float(np.median(distances.min(axis=1)))


@pytest.mark.parametrize("seed", range(5))
def test_frustum_scale_is_a_fraction_of_the_median_nearest_neighbour_distance(seed):
    rng = np.random.default_rng(seed)
    centres = rng.normal(size=(int(rng.integers(2, 60)), 3)) * rng.uniform(0.01, 10.0)
    with_twins = np.concatenate([centres, centres[: len(centres) // 2]])  # a camera at a place counts once
    expected = FRUSTUM_SPACING_FRACTION * _median_nearest_brute_force(centres)
    assert frustum_scale(centres) == pytest.approx(expected, rel=1e-12)
    assert frustum_scale(with_twins) == pytest.approx(expected, rel=1e-12)


def test_frustum_scale_without_spacing_falls_back():
    assert frustum_scale(np.zeros((1, 3))) == FRUSTUM_FALLBACK_SCALE
    assert frustum_scale(np.ones((5, 3))) == FRUSTUM_FALLBACK_SCALE  # every camera at one place
    assert frustum_scale(np.zeros((0, 3))) == FRUSTUM_FALLBACK_SCALE


def _covered(view_c2w: np.ndarray, view_fov: float, frustums: list[tuple[np.ndarray, float]], scale: float,
             samples: int = 200) -> float:
    """Share of a square view (vertical fov ``view_fov``) whose rays hit a frustum's image plane: the rectangle at
    depth ``scale`` along its camera's z axis, ``scale * tan(fov / 2)`` half a side (square images)."""
    half = math.tan(view_fov / 2)
    u, v = np.meshgrid(np.linspace(-half, half, samples), np.linspace(-half, half, samples))
    rays = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3) @ view_c2w[:3, :3].T
    origin, hit = view_c2w[:3, 3], np.zeros(len(rays), bool)
    for c2w, fov in frustums:
        normal, centre = c2w[:3, 2], c2w[:3, 3] + scale * c2w[:3, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = ((centre - origin) @ normal) / (rays @ normal)
        local = (origin + depth[:, None] * rays - centre) @ c2w[:3, :3]
        hit |= (depth > 0) & (np.abs(local[:, :2]) <= scale * math.tan(fov / 2)).all(axis=1)
    return float(hit.mean())


def test_frustums_of_a_dense_capture_leave_the_view_between_them_free():
    """100 cameras 1 cm apart along a line, all looking ahead (frames of a walk), with the viewer's camera halfway
    between two of them: the thumbnails cover almost none of its view (the earlier rule, 5 % of the cameras' extent,
    made each 5 cm deep, and the two beside the view covered most of it)."""
    fov = math.radians(50)
    poses = []
    for x in np.arange(100) * 0.01:
        c2w = np.eye(4)
        c2w[0, 3] = x
        poses.append(c2w)
    scale = frustum_scale(np.array([p[:3, 3] for p in poses]))
    view = np.eye(4)
    view[0, 3] = 0.495
    assert scale == pytest.approx(FRUSTUM_SPACING_FRACTION * 0.01)
    assert _covered(view, fov, [(p, fov) for p in poses], scale) < 0.02
    assert _covered(view, fov, [(p, fov) for p in poses], 0.05 * 0.495) > 0.5  # the old size: the view filled
