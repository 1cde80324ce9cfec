"""The generated demo scene: determinism, the 12/12 split, seed points on the analytic surfaces, exact images."""

import numpy as np
import pytest
import torch

from kc_splatfacto.data import resolve_dataparser
from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.demo import (
    DemoDataParserConfig,
    DemoSceneSpec,
    arc_cameras,
    build_scene,
    ensure_demo_scene,
    render_view,
)
from kc_splatfacto.data.images import read_image


@pytest.fixture(scope="module")
def demo_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("demo_cache")


@pytest.fixture(scope="module")
def demo_parser(demo_cache):
    return DemoDataParserConfig(demo_cache_dir=demo_cache).setup()


def box_sdf(points, center, half_size, yaw):
    """Signed distance to an oriented box (independent of the generator's ray caster)."""
    c, s = np.cos(yaw), np.sin(yaw)
    local = (points - center) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    q = np.abs(local) - half_size
    return np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)


def scene_distance(points, scene):
    dists = [np.abs(points @ p.normal - p.offset) for p in scene.planes]
    dists += [np.abs(box_sdf(points, b.center, b.half_size, b.yaw)) for b in scene.boxes]
    return np.min(np.stack(dists), axis=0)


def test_demo_split_is_12_train_12_test_alternating(demo_parser):
    train = demo_parser.get_dataparser_outputs("train")
    test = demo_parser.get_dataparser_outputs("test")
    val = demo_parser.get_dataparser_outputs("val")
    assert len(train.image_filenames) == 12 and len(test.image_filenames) == 12
    train_ids = [int(p.stem) for p in train.image_filenames]
    test_ids = [int(p.stem) for p in test.image_filenames]
    assert train_ids == list(range(0, 24, 2)) and test_ids == list(range(1, 24, 2))
    assert val.image_filenames == test.image_filenames
    assert int(train.cameras.widths[0]) == 160 and int(train.cameras.heights[0]) == 120
    assert train.points3d_xyz.shape == (2000, 3) and train.points3d_rgb.dtype == torch.uint8
    # normalized camera centres inside the unit cube, the largest coordinate exactly 1
    centers = torch.cat([train.cameras.centers(), test.cameras.centers()])
    assert centers.abs().max().item() == pytest.approx(1.0, abs=1e-5)


def test_demo_regenerated_with_same_seed_is_identical(tmp_path):
    small = {"width": 64, "height": 48, "num_points": 300}
    first = DemoDataParserConfig(demo_cache_dir=tmp_path / "a", **small).setup().get_dataparser_outputs("train")
    again = DemoDataParserConfig(demo_cache_dir=tmp_path / "b", **small).setup().get_dataparser_outputs("train")
    assert first.image_filenames[0].parent != again.image_filenames[0].parent  # really generated twice
    for a, b in zip(first.image_filenames, again.image_filenames):
        assert np.array_equal(read_image(a), read_image(b))
    assert torch.equal(first.cameras.viewmats, again.cameras.viewmats)
    assert torch.equal(first.points3d_xyz, again.points3d_xyz)
    other = DemoDataParserConfig(demo_cache_dir=tmp_path / "c", seed=1, num_cameras=2, **small).setup()
    other_image = read_image(other.get_dataparser_outputs("train").image_filenames[0])
    assert not np.array_equal(read_image(first.image_filenames[0]), other_image)


def test_demo_seed_points_lie_on_the_analytic_surfaces(demo_parser):
    outputs = demo_parser.get_dataparser_outputs("train")
    normalization = outputs.metadata["normalization"]
    world = normalization.invert_points(outputs.points3d_xyz.double().numpy())
    dist = scene_distance(world, build_scene(0))
    noise = DemoSceneSpec().point_noise
    # |N(0, s^2 I)| projected on a normal is N(0, s^2): 5 sigma bounds every one of 2000 points
    assert dist.max() < 5 * noise
    assert 0.3 * noise < np.median(dist) < 1.2 * noise  # the noise is really there, at the documented scale


def test_demo_seed_points_project_onto_their_surfaces_with_their_colour(demo_parser):
    """Project seed points with the parsed (normalized) cameras: where the surface is visible, the rendered depth
    matches the point's depth and the image colour matches the point's colour."""
    outputs = demo_parser.get_dataparser_outputs("train")
    dataset = ImageDataset(outputs)
    scene = build_scene(0)
    c2ws, intrinsics = arc_cameras(24, 160, 120)
    scale = outputs.dataparser_scale
    xyz = outputs.points3d_xyz.double()
    depth_errors, colour_errors = [], []
    for view in (0, 5, 11):
        viewmat = outputs.cameras.viewmats[view].double()
        cam = xyz @ viewmat[:3, :3].T + viewmat[:3, 3]
        uv = cam @ outputs.cameras.Ks[view].double().T
        uv = (uv[:, :2] / uv[:, 2:]).numpy()
        inside = (uv[:, 0] >= 0) & (uv[:, 0] < 160) & (uv[:, 1] >= 0) & (uv[:, 1] < 120) & (cam[:, 2].numpy() > 0)
        _, depth = render_view(scene, c2ws[2 * view], intrinsics, 160, 120)  # train view i is arc camera 2i
        cols, rows = uv[inside, 0].astype(int), uv[inside, 1].astype(int)
        point_depth = cam[inside, 2].numpy() / scale  # back to scene units
        visible = np.abs(depth[rows, cols] - point_depth) < 0.1
        assert visible.mean() > 0.6  # most seed points are seen by the views they were sampled from
        depth_errors.append(np.abs(depth[rows, cols] - point_depth)[visible])
        image = dataset.image_uint8(view).numpy().astype(float)
        colour_errors.append(np.abs(image[rows, cols] - outputs.points3d_rgb[inside].numpy())[visible].mean(axis=1))
    assert np.median(np.concatenate(depth_errors)) < 0.03
    assert np.median(np.concatenate(colour_errors)) < 25  # 8-bit levels; sharp texture edges make some large


def test_demo_images_are_heavy_tailed_like_photos(demo_parser):
    """Finest-scale horizontal differences (a Haar detail band) have kurtosis well above a Gaussian's 3."""
    outputs = demo_parser.get_dataparser_outputs("train")
    gray = read_image(outputs.image_filenames[0]).astype(float).mean(axis=2)
    detail = (gray[:, 1::2] - gray[:, 0::2]).ravel()
    detail = detail - detail.mean()
    kurtosis = np.mean(detail**4) / np.mean(detail**2) ** 2
    assert kurtosis > 6.0


def test_resolve_dataparser_demo_uses_the_cache_env(monkeypatch, tmp_path):
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(tmp_path))
    config = resolve_dataparser("demo")
    assert isinstance(config, DemoDataParserConfig)
    config.num_cameras = 4  # resizable and fast
    config.width, config.height = 32, 24
    config.num_points = 50
    outputs = config.setup().get_dataparser_outputs("train")
    assert outputs.image_filenames[0].is_relative_to(tmp_path / "demo")
    assert len(outputs.image_filenames) == 2 and int(outputs.cameras.widths[0]) == 32
    assert not list((tmp_path / "demo").glob(".*"))  # the temp generation folder is gone


def test_demo_spec_rejects_bad_sizes(tmp_path):
    with pytest.raises(DataParserError, match="too small"):
        ensure_demo_scene(DemoSceneSpec(width=4, height=4), tmp_path)
    with pytest.raises(DataParserError, match="at least 2 cameras"):
        ensure_demo_scene(DemoSceneSpec(num_cameras=1), tmp_path)


def test_unwritable_cache_is_a_clear_error(monkeypatch, tmp_path):
    blocker = tmp_path / "not_a_folder"
    blocker.write_text("a file where the cache folder should be")
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(blocker))
    with pytest.raises(DataParserError, match="cannot write the demo scene .*KC_SPLATFACTO_CACHE"):
        resolve_dataparser("demo").setup()
