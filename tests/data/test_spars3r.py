"""SPARS3R parser on castle-P30 (real data): split, seed points vs COLMAP tracks, normalization conventions."""

import warnings

import cv2
import numpy as np
import pytest
import torch

from kc_splatfacto.data import resolve_dataparser
from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.images import read_image
from kc_splatfacto.data.spars3r import Spars3rDataParserConfig
from tests.data_scenes import scene_variant


def test_castle_split_is_the_lists_with_seed_points(castle_p30):
    config = resolve_dataparser(castle_p30)
    assert isinstance(config, Spars3rDataParserConfig)
    parser = config.setup()
    train, test, val = (parser.get_dataparser_outputs(s) for s in ("train", "test", "val"))
    assert [p.name for p in train.image_filenames] == (castle_p30 / "train_list.txt").read_text().split()
    assert [p.name for p in test.image_filenames] == (castle_p30 / "test_list.txt").read_text().split()
    assert val.image_filenames == test.image_filenames  # "val" gets the test list
    assert len(train.cameras) == 12 and len(test.cameras) == 12
    assert train.points3d_xyz.shape == (1787, 3) and train.points3d_rgb.shape == (1787, 3)
    centers = torch.cat([train.cameras.centers(), test.cameras.centers()])
    assert centers.abs().max().item() <= 1.0 + 1e-5
    assert centers.abs().max().item() == pytest.approx(1.0, abs=1e-5)
    assert train.scene_scale == pytest.approx(1.0)
    # nerfstudio's "up" + "poses": the mean camera up (OpenGL +y = -OpenCV y column) is +z, the mean centre is 0
    c2w = torch.cat([train.cameras.camera_to_worlds(), test.cameras.camera_to_worlds()]).double()
    up = -c2w[:, :3, 1].mean(0)
    assert torch.allclose(up / up.norm(), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-5)
    assert centers.double().mean(0).abs().max().item() < 1e-5


def project(viewmat, K, xyz):
    cam = xyz @ viewmat[:3, :3].T + viewmat[:3, 3]
    uv = cam @ K.T
    return uv[:, :2] / uv[:, 2:], cam[:, 2]


def test_castle_seed_points_reproject_onto_their_track_keypoints(castle_p30, tmp_path):
    """Each seed point, projected with the parsed normalized and 2x-downscaled cameras into the train views of its
    COLMAP track, lands on the observed keypoint (read independently with pycolmap) within about a pixel."""
    pycolmap = pytest.importorskip("pycolmap")
    outputs = Spars3rDataParserConfig(data=castle_p30, downscale_factor=2, cache_dir=tmp_path).setup()
    outputs = outputs.get_dataparser_outputs("train")
    reconstruction = pycolmap.Reconstruction(str(castle_p30 / "sparse" / "0"))
    names = [p.name for p in outputs.image_filenames]
    # identify each COLMAP point among the seed points by position (the parser's transform, then nearest neighbour)
    transform = outputs.dataparser_transform.double()
    seeds = outputs.points3d_xyz.double()
    errors = []
    for point in reconstruction.points3D.values():
        expected = outputs.dataparser_scale * (transform[:, :3] @ torch.tensor(point.xyz) + transform[:, 3])
        distance, k = (seeds - expected).norm(dim=1).min(0)
        assert distance < 1e-5
        for element in point.track.elements:
            image = reconstruction.images[element.image_id]
            i = names.index(image.name)  # tracks only reference train views
            uv, depth = project(outputs.cameras.viewmats[i].double(), outputs.cameras.Ks[i].double(), seeds[k : k + 1])
            assert depth.item() > 0
            keypoint = torch.tensor(image.points2D[element.point2D_idx].xy) / 2.0
            errors.append((uv[0] - keypoint).norm().item())
    errors = np.array(errors)
    print(
        f"castle-P30 reprojection at 384x256: mean {errors.mean():.3f} px, "
        f"median {np.median(errors):.3f}, max {errors.max():.3f}"
    )
    assert len(errors) == 6089
    assert np.mean(errors) < 0.3 and np.median(errors) < 0.15  # README at full size: mean 0.299, median 0.159
    assert np.mean(errors < 1.0) > 0.98 and errors.max() < 2.5  # README max 3.93 px at full size
    # the downscaled images are OpenCV INTER_AREA resizes of the originals, at the cameras' size
    dataset = ImageDataset(outputs)
    original = read_image(castle_p30 / "images" / names[3])
    resized = cv2.resize(original, (384, 256), interpolation=cv2.INTER_AREA)
    assert (int(outputs.cameras.widths[3]), int(outputs.cameras.heights[3])) == (384, 256)
    assert np.abs(dataset.image_uint8(3).numpy().astype(int) - resized).mean() < 2.0  # JPEG re-encode only
    assert torch.allclose(outputs.cameras.Ks[3, 0], torch.tensor([689.87 / 2, 0.0, 380.1725 / 2]))


def test_test_images_missing_from_the_model_are_named_in_one_warning(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene", drop_model_images=("0004.jpg", "0019.jpg"))
    parser = Spars3rDataParserConfig(data=scene).setup()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        test = parser.get_dataparser_outputs("test")
    messages = [str(w.message) for w in caught if "left out" in str(w.message)]
    assert len(messages) == 1 and "0004.jpg" in messages[0] and "0019.jpg" in messages[0]
    assert len(test.image_filenames) == 10
    assert "0004.jpg" not in [p.name for p in test.image_filenames]


def test_train_image_missing_from_the_model_is_an_error(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene", drop_model_images=("0003.jpg",))
    with pytest.raises(DataParserError, match="0003.jpg.*no pose"):
        Spars3rDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
