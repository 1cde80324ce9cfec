"""transforms.json parser: castle-P30 cameras written as transforms.json parse back; skipped frames; PLY seeds;
nerfstudio's normalization and the dataparser_transforms.json file."""

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from kc_splatfacto.data import read_dataparser_transforms, resolve_dataparser, write_dataparser_transforms
from kc_splatfacto.data.base import (
    DataParserError,
    auto_orient_and_center_poses,
    normalize_poses,
    rotation_matrix_between,
)
from kc_splatfacto.data.spars3r import Spars3rDataParserConfig
from kc_splatfacto.data.transforms import TransformsDataParserConfig


def opengl_c2w(viewmats):
    c2w = torch.linalg.inv(viewmats.double()).numpy()
    c2w[:, :3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
    return c2w


def castle_outputs(castle_p30):
    parser = Spars3rDataParserConfig(data=castle_p30).setup()
    return parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")


def write_transforms(folder, outputs_list, extra=None, per_frame=False):
    frames = []
    meta = {"camera_model": "OPENCV", "aabb_scale": 16}
    for outputs in outputs_list:
        for path, c2w, K, w, h in zip(
            outputs.image_filenames,
            opengl_c2w(outputs.cameras.viewmats),
            outputs.cameras.Ks.double().numpy(),
            outputs.cameras.widths.tolist(),
            outputs.cameras.heights.tolist(),
        ):
            # images copied in (names relative to the json: absolute ones and symlinks out are refused)
            (folder / "images").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(path, folder / "images" / Path(path).name)
            frame = {"file_path": f"images/{Path(path).name}", "transform_matrix": c2w.tolist()}
            intrinsics = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": w, "h": h}
            (frame if per_frame else meta).update(intrinsics)
            frames.append(frame)
    meta["frames"] = frames
    meta.update(extra or {})
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "transforms.json").write_text(json.dumps(meta))
    return folder


@pytest.mark.parametrize("per_frame", [False, True])
def test_castle_cameras_written_as_transforms_json_parse_back(castle_p30, tmp_path, per_frame):
    train, test = castle_outputs(castle_p30)
    split = {
        "train_filenames": [f"images/{p.name}" for p in train.image_filenames],
        "test_filenames": [f"images/{p.name}" for p in test.image_filenames],
    }
    scene = write_transforms(tmp_path / "ns", [train, test], split, per_frame=per_frame)
    config = resolve_dataparser(scene)
    assert isinstance(config, TransformsDataParserConfig)
    parser = config.setup()
    for original, split_name in ((train, "train"), (test, "test"), (test, "val")):
        parsed = parser.get_dataparser_outputs(split_name)
        assert parsed.image_filenames == [scene / "images" / p.name for p in original.image_filenames]
        # already normalized poses are a fixed point of the normalization: same cameras
        assert torch.allclose(parsed.cameras.viewmats, original.cameras.viewmats, atol=1e-5)
        assert torch.allclose(parsed.cameras.Ks, original.cameras.Ks, atol=1e-5)
        assert torch.equal(parsed.cameras.widths, original.cameras.widths)
        assert torch.equal(parsed.cameras.heights, original.cameras.heights)
    assert torch.allclose(parser.get_dataparser_outputs("train").dataparser_transform, torch.eye(4)[:3], atol=1e-5)


def test_raw_world_transforms_json_round_trips_through_the_reported_transform(castle_p30, tmp_path):
    """Poses in an arbitrary world: the reported (transform, scale) maps that world onto the parsed cameras."""
    train, test = castle_outputs(castle_p30)
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    similarity = np.eye(4)
    similarity[:3, :3], similarity[:3, 3] = 3.7 * q, rng.normal(size=3) * 5  # world = 3.7 R x + t
    scene = tmp_path / "raw"
    write_transforms(scene, [train, test])
    meta = json.loads((scene / "transforms.json").read_text())
    for frame in meta["frames"]:
        c2w = similarity @ np.array(frame["transform_matrix"])
        c2w[:3, :3] /= 3.7  # keep a rotation: only the centre moves by the similarity's scale
        frame["transform_matrix"] = c2w.tolist()
    (scene / "transforms.json").write_text(json.dumps(meta))
    parsed = TransformsDataParserConfig(data=scene, eval_mode="all").setup().get_dataparser_outputs("train")
    world_centers = np.array([np.array(f["transform_matrix"])[:3, 3] for f in meta["frames"]])
    order = np.argsort([f["file_path"] for f in meta["frames"]])  # frames are sorted by file name
    transform, scale = parsed.dataparser_transform.double().numpy(), parsed.dataparser_scale
    mapped = scale * (world_centers[order] @ transform[:, :3].T + transform[:, 3])
    assert np.allclose(mapped, parsed.cameras.centers().double().numpy(), atol=1e-5)
    assert np.abs(mapped).max() == pytest.approx(1.0, abs=1e-6)


def test_frames_with_missing_images_are_named_and_skipped(castle_p30, tmp_path):
    train, test = castle_outputs(castle_p30)
    scene = write_transforms(tmp_path / "ns", [train, test])
    meta = json.loads((scene / "transforms.json").read_text())
    meta["frames"][3]["file_path"] = "images/ghost_a.jpg"
    meta["frames"][7]["file_path"] = "images/ghost_b.jpg"
    (scene / "transforms.json").write_text(json.dumps(meta))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        outputs = TransformsDataParserConfig(data=scene, eval_mode="all").setup().get_dataparser_outputs("train")
    messages = [str(w.message) for w in caught if "skipped" in str(w.message)]
    assert len(messages) == 1 and "ghost_a.jpg" in messages[0] and "ghost_b.jpg" in messages[0]
    assert len(outputs.image_filenames) == 22


def test_ply_seed_points_get_the_pose_normalization(castle_p30, tmp_path):
    trimesh = pytest.importorskip("trimesh")
    train, test = castle_outputs(castle_p30)
    world = train.points3d_xyz.double().numpy() * 2.0 + 1.0  # a world that needs normalizing
    colours = train.points3d_rgb.numpy()
    scene = tmp_path / "ns"
    write_transforms(scene, [train, test], {"ply_file_path": "points.ply"})
    trimesh.PointCloud(world, colors=np.concatenate([colours, np.full((len(colours), 1), 255, np.uint8)], 1)).export(
        str(scene / "points.ply")
    )
    meta = json.loads((scene / "transforms.json").read_text())
    for frame in meta["frames"]:
        c2w = np.array(frame["transform_matrix"])
        c2w[:3, 3] = c2w[:3, 3] * 2.0 + 1.0
        frame["transform_matrix"] = c2w.tolist()
    (scene / "transforms.json").write_text(json.dumps(meta))
    parsed = TransformsDataParserConfig(data=scene, eval_mode="all").setup().get_dataparser_outputs("train")
    # the similarity (x2, +1) is undone: points land where the normalized castle points were
    assert torch.allclose(parsed.points3d_xyz, train.points3d_xyz, atol=1e-5)
    assert torch.equal(parsed.points3d_rgb, train.points3d_rgb)


def test_transforms_bad_inputs(tmp_path):
    with pytest.raises(DataParserError, match="transforms.json does not exist"):
        TransformsDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")
    (tmp_path / "transforms.json").write_text("{not json")
    with pytest.raises(DataParserError, match="not valid JSON"):
        TransformsDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")
    (tmp_path / "img.png").write_bytes(b"")
    frame = {"file_path": "img.png", "transform_matrix": np.eye(4).tolist()}
    (tmp_path / "transforms.json").write_text(
        json.dumps({"frames": [frame], "fl_x": 50, "cx": 5, "cy": 5, "w": 10, "h": 10})
    )
    with pytest.raises(DataParserError, match="'fl_y'"):
        TransformsDataParserConfig(data=tmp_path, eval_mode="all").setup().get_dataparser_outputs("train")
    fisheye = {
        "frames": [frame],
        "camera_model": "OPENCV_FISHEYE",
        "fl_x": 5,
        "fl_y": 5,
        "cx": 5,
        "cy": 5,
        "w": 10,
        "h": 10,
    }
    (tmp_path / "transforms.json").write_text(json.dumps(fisheye))
    with pytest.raises(DataParserError, match="OPENCV_FISHEYE"):
        TransformsDataParserConfig(data=tmp_path, eval_mode="all").setup().get_dataparser_outputs("train")
    nan_frame = {"file_path": "img.png", "transform_matrix": [[float("nan")] * 4] * 4}
    (tmp_path / "transforms.json").write_text(json.dumps({"frames": [nan_frame]}))
    with pytest.raises(DataParserError, match=r"frames\[0\].transform_matrix contains NaN"):
        TransformsDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")


# ---------------------------------------------------------------------------------------------------------------
# normalization and the transform file
# ---------------------------------------------------------------------------------------------------------------


def test_rotation_matrix_between_matches_scipy_shortest_arc():
    rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        expected, _ = rotation.align_vectors(b[None] / np.linalg.norm(b), a[None] / np.linalg.norm(a))
        assert np.allclose(rotation_matrix_between(a, b), expected.as_matrix(), atol=1e-9)
    # parallel and opposite vectors: still a proper rotation taking a onto b
    for a, b in (([0, 0, 1.0], [0, 0, 2.0]), ([0, 0, 1.0], [0, 0, -1.0]), ([1.0, 0, 0], [-1.0, 0, 0])):
        r = rotation_matrix_between(np.array(a), np.array(b))
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-9) and np.linalg.det(r) == pytest.approx(1.0)
        assert np.allclose(r @ (np.array(a) / np.linalg.norm(a)), np.array(b) / np.linalg.norm(b), atol=1e-9)


def test_normalization_is_nerfstudio_up_poses_unit_cube():
    """Random OpenGL poses: the oriented mean up is +z, the mean centre 0, and the largest |coordinate| 1."""
    rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    rng = np.random.default_rng(4)
    c2w_gl = np.tile(np.eye(4), (9, 1, 1))
    c2w_gl[:, :3, :3] = rotation.random(9, random_state=5).as_matrix()
    c2w_gl[:, :3, 3] = rng.normal(size=(9, 3)) * 4 + 10
    oriented, _ = auto_orient_and_center_poses(c2w_gl)
    up = oriented[:, :3, 1].mean(0)
    assert np.allclose(up / np.linalg.norm(up), [0, 0, 1], atol=1e-9)
    assert np.allclose(oriented[:, :3, 3].mean(0), 0, atol=1e-9)
    c2w_cv = c2w_gl.copy()
    c2w_cv[:, :3, 1:3] *= -1
    normalization = normalize_poses(c2w_cv)
    centers = normalization.apply_to_c2w(c2w_cv)[:, :3, 3]
    assert np.abs(centers).max() == pytest.approx(1.0)
    assert np.allclose(centers, oriented[:, :3, 3] * normalization.scale, atol=1e-9)
    # the inverse maps points back
    points = rng.normal(size=(5, 3))
    assert np.allclose(normalization.invert_points(normalization.apply_to_points(points)), points, atol=1e-9)
    with pytest.raises(DataParserError, match=r"camera poses \[2\] contain NaN"):
        bad = c2w_cv.copy()
        bad[2, 0, 3] = np.nan
        normalize_poses(bad)


def test_dataparser_transforms_json_round_trip(castle_p30, tmp_path):
    train, _ = castle_outputs(castle_p30)
    path = write_dataparser_transforms(tmp_path / "run" / "dataparser_transforms.json", train)
    payload = json.loads(path.read_text())
    assert set(payload) == {"transform", "scale"}
    assert np.array(payload["transform"]).shape == (3, 4)
    assert payload["scale"] == pytest.approx(train.dataparser_scale)
    back = read_dataparser_transforms(path)
    pycolmap = pytest.importorskip("pycolmap")
    first = next(iter(pycolmap.Reconstruction(str(castle_p30 / "sparse" / "0")).points3D.values()))
    mapped = back.apply_to_points(np.array(first.xyz)[None])
    assert np.abs(train.points3d_xyz.double().numpy() - mapped).sum(axis=1).min() < 1e-5
    with pytest.raises(DataParserError, match="does not exist"):
        read_dataparser_transforms(tmp_path / "nope.json")


def test_single_camera_normalizes_without_dividing_by_zero():
    c2w = np.eye(4)
    c2w[:3, 3] = [3.0, -2.0, 5.0]
    normalization = normalize_poses(c2w[None])
    assert normalization.scale == 1.0  # zero extent: unit scale, never inf/NaN
    assert np.allclose(normalization.apply_to_c2w(c2w[None])[0, :3, 3], 0.0)
    assert np.isfinite(normalization.transform).all()


def test_masks_follow_their_images_through_downscaling(castle_p30, tmp_path):
    import cv2

    from kc_splatfacto.data.dataset import ImageDataset

    train, _ = castle_outputs(castle_p30)
    scene = write_transforms(tmp_path / "ns", [train])
    meta = json.loads((scene / "transforms.json").read_text())
    rng = np.random.default_rng(7)
    masks = {}
    for frame in meta["frames"][:12]:
        mask = np.zeros((512, 768), np.uint8)
        x, y = rng.integers(0, 600), rng.integers(0, 400)
        mask[y : y + 100, x : x + 150] = 255
        name = f"masks/{Path(frame['file_path']).stem}.png"
        (scene / "masks").mkdir(exist_ok=True)
        cv2.imwrite(str(scene / name), mask)
        frame["mask_path"] = name
        masks[Path(frame["file_path"]).name] = mask
    (scene / "transforms.json").write_text(json.dumps(meta))
    config = TransformsDataParserConfig(data=scene, eval_mode="all", downscale_factor=2, cache_dir=tmp_path / "cache")
    outputs = config.setup().get_dataparser_outputs("train")
    dataset = ImageDataset(outputs)
    for i in (0, 5):
        expected = cv2.resize(masks[outputs.image_filenames[i].name], (384, 256), interpolation=cv2.INTER_AREA) > 127
        got = dataset.mask(i)
        assert got.shape == (256, 384, 1) and got.dtype == torch.bool
        assert np.array_equal(got[..., 0].numpy(), expected)
    del meta["frames"][3]["mask_path"]
    (scene / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataParserError, match="some frames .* have a mask_path and others do not"):
        config.setup().get_dataparser_outputs("train")


def test_blender_style_camera_angle_x_with_rgba_images(tmp_path):
    """NeRF-synthetic layout: camera_angle_x only, extension-less paths, RGBA PNGs composited on the background."""
    import cv2

    from kc_splatfacto.data.dataset import ImageDataset

    (tmp_path / "train").mkdir()
    frames = []
    for i in range(3):
        rgba = np.zeros((30, 40, 4), np.uint8)
        rgba[10:20, 10:30] = (255, 0, 0, 255)  # opaque blue square in BGRA
        cv2.imwrite(str(tmp_path / "train" / f"r_{i}.png"), rgba)
        c2w = np.eye(4)
        c2w[:3, 3] = [i, 0.0, 4.0]
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": c2w.tolist()})
    angle = 0.6911112070083618
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))
    outputs = TransformsDataParserConfig(data=tmp_path, eval_mode="all").setup().get_dataparser_outputs("train")
    focal = 20.0 / np.tan(angle / 2)
    expected_k = torch.tensor([[focal, 0, 20.0], [0, focal, 15.0], [0, 0, 1]], dtype=torch.float32)
    assert torch.allclose(outputs.cameras.Ks[0], expected_k)
    assert int(outputs.cameras.widths[0]) == 40 and int(outputs.cameras.heights[0]) == 30
    dataset = ImageDataset(outputs)
    image = dataset.image_uint8(1)  # RGBA kept: the model composites it over the background it renders with
    assert image[0, 0].tolist() == [0, 0, 0, 0] and image[15, 20].tolist() == [0, 0, 255, 255]
    assert int((image[..., 3] > 127).sum()) == 200 and dataset.mask(1) is None


# ------------------------------------------------------------------------------------------------ issue 26


def tiny_transforms(tmp_path):
    from tests.hostile_scenes import transforms_scene

    return transforms_scene(tmp_path / "scene")


def parse_cameras(scene):
    parser = TransformsDataParserConfig(data=scene).setup()
    return parser.get_dataparser_outputs("train").cameras


def test_3x4_and_4x4_matrices_may_mix_and_give_the_same_cameras(tmp_path):
    scene = tiny_transforms(tmp_path)
    reference = parse_cameras(scene)
    path = scene / "transforms.json"
    meta = json.loads(path.read_text())
    for frame in meta["frames"][::2]:
        frame["transform_matrix"] = frame["transform_matrix"][:3]
    path.write_text(json.dumps(meta))
    mixed = parse_cameras(scene)
    assert torch.equal(mixed.viewmats, reference.viewmats) and torch.equal(mixed.Ks, reference.Ks)


def test_transforms_json_with_a_byte_order_mark_parses(tmp_path):
    scene = tiny_transforms(tmp_path)
    reference = parse_cameras(scene)
    path = scene / "transforms.json"
    path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    assert torch.equal(parse_cameras(scene).viewmats, reference.viewmats)


def test_rotation_within_rounding_is_accepted_and_beyond_it_refused(tmp_path):
    scene = tiny_transforms(tmp_path)
    path = scene / "transforms.json"
    meta = json.loads(path.read_text())
    original = json.dumps(meta)
    for scale, accepted in ((1.0 + 1e-5, True), (1.01, False)):
        meta = json.loads(original)
        matrix = np.asarray(meta["frames"][1]["transform_matrix"])
        matrix[:3, :3] *= scale
        meta["frames"][1]["transform_matrix"] = matrix.tolist()
        path.write_text(json.dumps(meta))
        if accepted:
            parse_cameras(scene)
        else:
            with pytest.raises(DataParserError, match=r"frames\[1\].transform_matrix: its 3x3 rotation part is not orthonormal"):
                parse_cameras(scene)
