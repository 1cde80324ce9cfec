"""COLMAP parser on fountain-P11 (real data): eval modes, camera models, undistortion against OpenCV's projection."""

import shutil

import cv2
import numpy as np
import pytest
import torch

from kc_splatfacto.data import resolve_dataparser
from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.colmap import ColmapDataParserConfig
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.images import read_image
from tests.data_scenes import scene_variant

FOUNTAIN_NAMES = [f"{i:04d}.jpg" for i in range(11)]
FOUNTAIN_K = (689.87, 691.04, 380.1725, 251.7025)


def names(outputs):
    return [p.name for p in outputs.image_filenames]


@pytest.mark.parametrize(
    "eval_mode, train, test",
    [
        ("interval", [n for i, n in enumerate(FOUNTAIN_NAMES) if i % 8 != 0], ["0000.jpg", "0008.jpg"]),
        # ceil(11 * 0.9) = 10 train images spread by linspace(0, 10, 10).astype(int): index 9 is left for eval
        ("fraction", [n for i, n in enumerate(FOUNTAIN_NAMES) if i != 9], ["0009.jpg"]),
        ("all", FOUNTAIN_NAMES, FOUNTAIN_NAMES),
    ],
)
def test_fountain_eval_modes(fountain_p11, eval_mode, train, test):
    config = resolve_dataparser(fountain_p11)
    assert isinstance(config, ColmapDataParserConfig)
    config.eval_mode = eval_mode
    parser = config.setup()
    train_out, test_out = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    assert names(train_out) == train and names(test_out) == test
    assert names(parser.get_dataparser_outputs("val")) == test
    assert train_out.points3d_xyz.shape == (4761, 3)
    # one world for both splits: normalized on all 11 poses, whatever the split
    assert torch.equal(train_out.dataparser_transform, test_out.dataparser_transform)
    centers = torch.cat([train_out.cameras.centers(), test_out.cameras.centers()])
    assert centers.abs().max().item() <= 1.0 + 1e-5
    assert torch.allclose(
        train_out.cameras.Ks[0],
        torch.tensor([[FOUNTAIN_K[0], 0, FOUNTAIN_K[2]], [0, FOUNTAIN_K[1], FOUNTAIN_K[3]], [0, 0, 1.0]]),
    )


def test_fountain_filename_mode(fountain_p11, tmp_path):
    with pytest.raises(DataParserError, match="'0000.jpg' has neither"):
        ColmapDataParserConfig(data=fountain_p11, eval_mode="filename").setup().get_dataparser_outputs("train")
    renamed = scene_variant(
        fountain_p11,
        tmp_path / "scene",
        with_lists=False,
        rename=lambda n: ("eval_" if int(n[:4]) % 3 == 0 else "train_") + n,
    )
    parser = ColmapDataParserConfig(data=renamed, eval_mode="filename").setup()
    assert names(parser.get_dataparser_outputs("test")) == [
        "eval_0000.jpg",
        "eval_0003.jpg",
        "eval_0006.jpg",
        "eval_0009.jpg",
    ]
    assert len(parser.get_dataparser_outputs("train").image_filenames) == 7


def test_fountain_seed_points_reproject_onto_keypoints(fountain_p11):
    """Seed points into every view of their track (all 11 views are train in eval mode 'all')."""
    pycolmap = pytest.importorskip("pycolmap")
    outputs = ColmapDataParserConfig(data=fountain_p11, eval_mode="all").setup().get_dataparser_outputs("train")
    reconstruction = pycolmap.Reconstruction(str(fountain_p11 / "sparse" / "0"))
    transform, scale = outputs.dataparser_transform.double(), outputs.dataparser_scale
    errors = []
    for point in list(reconstruction.points3D.values())[::10]:
        xyz = scale * (transform[:, :3] @ torch.tensor(point.xyz) + transform[:, 3])
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            i = names(outputs).index(image.name)
            cam = outputs.cameras.viewmats[i, :3, :3].double() @ xyz + outputs.cameras.viewmats[i, :3, 3].double()
            uv = (outputs.cameras.Ks[i].double() @ cam)[:2] / cam[2]
            errors.append((uv - torch.tensor(image.points2D[element.point2D_idx].xy)).norm().item())
    assert np.median(errors) < 0.3 and np.mean(errors) < 0.5  # README: 0.256 px per observation


def camera_line(model, params):
    return f"1 {model} 768 512 {' '.join(repr(float(p)) for p in params)}\n"


@pytest.mark.parametrize(
    "model, params, distortion",
    [
        ("SIMPLE_PINHOLE", [690.0, 380.0, 250.0], None),
        ("SIMPLE_RADIAL", [690.0, 380.0, 250.0, -0.08], [-0.08, 0, 0, 0, 0]),
        ("RADIAL", [690.0, 380.0, 250.0, -0.06, 0.02], [-0.06, 0.02, 0, 0, 0]),
        ("OPENCV", [689.87, 691.04, 380.1725, 251.7025, -0.05, 0.01, 0.001, -0.002], [-0.05, 0.01, 0.001, -0.002, 0]),
    ],
)
def test_camera_models_and_undistortion(fountain_p11, tmp_path, model, params, distortion):
    """The parsed pinhole of an undistorted image sees the same scene point as the distorted original:
    a pixel of the undistorted image equals the original image sampled where OpenCV's projection with the
    original (distorted) camera sends that pixel's ray."""
    scene = scene_variant(fountain_p11, tmp_path / "scene", with_lists=False, cameras_txt=camera_line(model, params))
    config = ColmapDataParserConfig(data=scene, eval_mode="all", cache_dir=tmp_path / "cache")
    outputs = config.setup().get_dataparser_outputs("test")
    k_new = outputs.cameras.Ks[2].double().numpy()
    width, height = int(outputs.cameras.widths[2]), int(outputs.cameras.heights[2])
    if distortion is None:
        fx = params[0]
        assert np.allclose(k_new, [[fx, 0, params[1]], [0, fx, params[2]], [0, 0, 1]])
        assert outputs.image_filenames[2] == scene / "images" / "0002.jpg"  # nothing to undistort
        return
    assert outputs.image_filenames[2].is_relative_to(tmp_path / "cache")  # cached copy, scene folder untouched
    assert 0.8 * 768 < width <= 768 and 0.8 * 512 < height <= 512
    undistorted = ImageDataset(outputs).image_uint8(2).numpy().astype(np.float32)
    original = read_image(scene / "images" / "0002.jpg").astype(np.float32)
    fx, fy, cx, cy = (params + [0])[:4] if model == "OPENCV" else (params[0], params[0], params[1], params[2])
    k_orig = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    # rays through every 7th pixel centre of the undistorted image (centres at +0.5)
    jj, ii = np.meshgrid(np.arange(5, width - 5, 7), np.arange(5, height - 5, 7))
    pix = np.stack([jj.ravel() + 0.5, ii.ravel() + 0.5, np.ones(jj.size)], axis=1)
    rays = pix @ np.linalg.inv(k_new).T
    projected, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), k_orig, np.array(distortion, np.float64))
    projected = projected.reshape(-1, 2) - 0.5  # to OpenCV's integer pixel centres for remap
    sampled = cv2.remap(original, projected[:, None, :].astype(np.float32), None, cv2.INTER_LINEAR)[:, 0]
    diff = np.abs(sampled - undistorted[ii.ravel(), jj.ravel()]).mean()
    shifted = np.abs(sampled - undistorted[ii.ravel(), jj.ravel() + 2]).mean()
    print(f"{model}: undistortion mean abs diff {diff:.2f} levels, 2-px shifted {shifted:.2f}")
    # 0.25 levels measured; half a pixel off (the OpenCV vs COLMAP pixel-centre trap) gives about 2
    assert diff < 1.0 and diff < 0.2 * shifted
    # second parse reuses the cached files
    mtime = outputs.image_filenames[2].stat().st_mtime_ns
    config.setup().get_dataparser_outputs("test")
    assert outputs.image_filenames[2].stat().st_mtime_ns == mtime
    if model == "OPENCV":  # undistort then downscale: INTER_AREA of the undistorted image, intrinsics scaled
        config.downscale_factor, config.eval_mode = 2, "interval"
        small = config.setup().get_dataparser_outputs("test")  # 0000.jpg and 0008.jpg
        assert names(small) == ["0000.png", "0008.png"]  # undistorted copies are PNG
        big_index = [p.stem for p in outputs.image_filenames].index("0008")
        full = ImageDataset(outputs).image_uint8(big_index).numpy()
        w2, h2 = full.shape[1] // 2, full.shape[0] // 2
        assert (int(small.cameras.widths[1]), int(small.cameras.heights[1])) == (w2, h2)
        expected = cv2.resize(full, (w2, h2), interpolation=cv2.INTER_AREA)
        assert np.array_equal(ImageDataset(small).image_uint8(1).numpy(), expected)
        k_full = outputs.cameras.Ks[big_index].double()
        ratio = torch.tensor([w2 / full.shape[1], h2 / full.shape[0], 1.0], dtype=torch.float64)
        assert torch.allclose(small.cameras.Ks[1].double(), k_full * ratio[:, None], atol=1e-4)


def test_unsupported_camera_model_is_named(fountain_p11, tmp_path):
    line = camera_line("OPENCV_FISHEYE", [690, 690, 380, 250, 0.1, 0.0, 0.0, 0.0])
    scene = scene_variant(fountain_p11, tmp_path / "scene", with_lists=False, cameras_txt=line)
    with pytest.raises(DataParserError, match="OPENCV_FISHEYE, which is not supported.*PINHOLE"):
        ColmapDataParserConfig(data=scene).setup().get_dataparser_outputs("train")


def visible(folder):
    """Entries of ``folder`` without the hidden ones (the ``.sources`` records of derived images)."""
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


def read_only_copy(src, dst):
    """A copy of a scene whose folders are read-only by their mode bits (what ``folder_is_writable`` checks, so the
    test does not depend on how ../shared is mounted or on running as root)."""
    shutil.copytree(src, dst)
    for folder in [dst, *[p for p in dst.rglob("*") if p.is_dir()]]:
        folder.chmod(0o555)
    return dst


def test_downscale_cache_is_reused_and_written_outside_read_only_scenes(fountain_p11, tmp_path, monkeypatch):
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(tmp_path / "user_cache"))
    scene = read_only_copy(fountain_p11, tmp_path / "scene")
    before = sorted(str(p) for p in scene.rglob("*"))
    try:
        config = ColmapDataParserConfig(data=scene, downscale_factor=4)
        outputs = config.setup().get_dataparser_outputs("test")  # 2 images only: the split's
        for path in outputs.image_filenames:
            assert path.is_relative_to(tmp_path / "user_cache")  # the scene is read-only: user cache used
            assert path.parent.name == "images_4"
        assert visible(outputs.image_filenames[0].parent) == ["0000.jpg", "0008.jpg"]
        assert (int(outputs.cameras.widths[0]), int(outputs.cameras.heights[0])) == (192, 128)
        assert torch.allclose(outputs.cameras.Ks[0, 0, 0], torch.tensor(FOUNTAIN_K[0] / 4))
        assert read_image(outputs.image_filenames[0]).shape == (128, 192, 3)
        assert not list(outputs.image_filenames[0].parent.rglob("*.tmp"))  # atomic writes leave no temp files
        mtime = outputs.image_filenames[0].stat().st_mtime_ns
        config.setup().get_dataparser_outputs("test")
        assert outputs.image_filenames[0].stat().st_mtime_ns == mtime  # reused, not rewritten
        assert sorted(str(p) for p in scene.rglob("*")) == before  # nothing written into the scene
    finally:
        for folder in [scene, *[p for p in scene.rglob("*") if p.is_dir()]]:
            folder.chmod(0o755)


def test_downscaled_copy_is_rebuilt_when_its_source_changes(fountain_p11, tmp_path):
    """images_N/ entries are keyed on the source's size and mtime: an edited source image is resized again."""
    scene = scene_variant(fountain_p11, tmp_path / "scene", with_lists=False)
    config = ColmapDataParserConfig(data=scene, downscale_factor=2)
    first = config.setup().get_dataparser_outputs("test").image_filenames[0]
    source = scene / "images" / "0000.jpg"
    original = read_image(source)
    flipped = np.ascontiguousarray(original[::-1])  # same size, different content
    cv2.imwrite(str(source), cv2.cvtColor(flipped, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 98])
    again = config.setup().get_dataparser_outputs("test").image_filenames[0]
    assert again == first
    size = (original.shape[1] // 2, original.shape[0] // 2)
    new_expected = cv2.resize(read_image(source), size, interpolation=cv2.INTER_AREA).astype(np.float64)
    old_expected = cv2.resize(original, size, interpolation=cv2.INTER_AREA).astype(np.float64)
    got = read_image(again).astype(np.float64)
    # the copy is a JPEG (quality 95): within JPEG error of the new source, far from the old one
    assert np.abs(got - new_expected).mean() < 2.0 < 10 * 2.0 < np.abs(got - old_expected).mean()


def test_downscale_that_leaves_no_pixels_is_refused_before_anything_is_written(fountain_p11, tmp_path):
    """Checked up front: not after the distorted images were already undistorted into the cache."""
    line = camera_line("OPENCV", [*FOUNTAIN_K, -0.05, 0.01, 0.0, 0.0])
    scene = scene_variant(fountain_p11, tmp_path / "scene", with_lists=False, cameras_txt=line)
    before = sorted(p.name for p in scene.iterdir())
    config = ColmapDataParserConfig(data=scene, downscale_factor=1000)  # 768x512 images
    with pytest.raises(DataParserError, match="downscale_factor 1000 is too large"):
        config.setup().get_dataparser_outputs("train")
    assert sorted(p.name for p in scene.iterdir()) == before  # no images_undistorted_*/, no images_1000/


def nerfstudio_colmap_reference(world_to_cameras):
    """A float32 torch transcription of nerfstudio's COLMAP path (colmap_dataparser + camera_utils defaults):
    OpenCV -> OpenGL flip, COLMAP world convention (x, z, -y), orient "up", centre "poses", auto scale."""
    poses = []
    for w2c in world_to_cameras:
        c2w = np.linalg.inv(w2c)
        c2w[0:3, 1:3] *= -1
        c2w = c2w[np.array([0, 2, 1, 3]), :]  # assume_colmap_world_coordinate_convention (the default)
        c2w[2, :] *= -1
        poses.append(c2w)
    poses = torch.from_numpy(np.array(poses).astype(np.float32))
    mean_origin = poses[..., :3, 3].mean(dim=0)
    up = poses[:, :3, 1].mean(dim=0)
    a, b = up / up.norm(), torch.tensor([0.0, 0.0, 1.0])
    v = torch.linalg.cross(a, b)
    v = v / v.norm()
    skew = torch.tensor([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    theta = torch.acos(torch.clip(torch.dot(a, b), -1, 1))
    rotation = torch.eye(3) + torch.sin(theta) * skew + (1 - torch.cos(theta)) * (skew @ skew)
    transform = torch.cat([rotation, rotation @ -mean_origin[..., None]], dim=-1)
    oriented = transform @ poses
    scale = 1.0 / float(torch.max(torch.abs(oriented[:, :3, 3])))
    oriented[:, :3, 3] *= scale
    applied = torch.eye(4)[:3, :][torch.tensor([0, 2, 1]), :]
    applied[2, :] *= -1
    transform = transform @ torch.cat([applied, torch.tensor([[0, 0, 0, 1.0]])], 0)
    return oriented, transform, scale


def test_fountain_normalization_matches_nerfstudio_reference(fountain_p11):
    pycolmap = pytest.importorskip("pycolmap")
    reconstruction = pycolmap.Reconstruction(str(fountain_p11 / "sparse" / "0"))
    images = sorted(reconstruction.images.values(), key=lambda im: im.name)
    w2cs = []
    for image in images:
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        w2cs.append(w2c)
    ref_c2w_gl, ref_transform, ref_scale = nerfstudio_colmap_reference(w2cs)
    outputs = ColmapDataParserConfig(data=fountain_p11, eval_mode="all").setup().get_dataparser_outputs("train")
    c2w_gl = outputs.cameras.camera_to_worlds().clone()
    c2w_gl[:, :3, 1:3] *= -1
    assert torch.allclose(c2w_gl[:, :3, :4], ref_c2w_gl[:, :3, :4], atol=1e-5)
    assert torch.allclose(outputs.dataparser_transform, ref_transform, atol=1e-5)
    assert outputs.dataparser_scale == pytest.approx(ref_scale, rel=1e-6)


def test_colmap_masks_path(fountain_p11, tmp_path):
    scene = scene_variant(fountain_p11, tmp_path / "scene", with_lists=False)
    (scene / "masks").mkdir()
    expected = {}
    for i, name in enumerate(FOUNTAIN_NAMES):
        mask = np.zeros((512, 768), np.uint8)
        mask[:, : 60 * (i + 1)] = 255
        cv2.imwrite(str(scene / "masks" / name.replace(".jpg", ".png")), mask)
        expected[name] = mask > 127
    outputs = ColmapDataParserConfig(data=scene, masks_path="masks").setup().get_dataparser_outputs("test")
    dataset = ImageDataset(outputs)
    assert names(outputs) == ["0000.jpg", "0008.jpg"]
    for i, name in enumerate(names(outputs)):
        assert np.array_equal(dataset.mask(i)[..., 0].numpy(), expected[name])
    (scene / "masks" / "0008.png").unlink()
    with pytest.raises(DataParserError, match="mask file.* missing: .*0008.png"):
        ColmapDataParserConfig(data=scene, masks_path="masks").setup().get_dataparser_outputs("test")


def test_downscale_into_a_writable_scene_folder_split_by_split(fountain_p11, tmp_path):
    """Each split writes only its own images into <scene>/images_2; the next split adds its own."""
    scene = scene_variant(fountain_p11, tmp_path / "scene", with_lists=False)
    config = ColmapDataParserConfig(data=scene, downscale_factor=2)
    test = config.setup().get_dataparser_outputs("test")
    assert [p.parent for p in test.image_filenames] == [scene / "images_2"] * 2
    assert visible(scene / "images_2") == ["0000.jpg", "0008.jpg"]
    train = config.setup().get_dataparser_outputs("train")
    assert len(visible(scene / "images_2")) == 11
    assert all(p.parent == scene / "images_2" for p in train.image_filenames)
    assert read_image(train.image_filenames[0]).shape == (256, 384, 3)
