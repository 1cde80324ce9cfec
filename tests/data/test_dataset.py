"""ImageDataset: lazy uint8 images of one split, float conversion, RGBA compositing against a numpy oracle."""

import cv2
import numpy as np
import pytest
import torch

from kc_splatfacto.data.base import DataParserError, make_cameras
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.outputs import DataparserOutputs


def write_png(path, array):
    path.parent.mkdir(parents=True, exist_ok=True)
    if array.shape[2] == 4:
        bgr = cv2.cvtColor(array, cv2.COLOR_RGBA2BGRA)
    else:
        bgr = cv2.cvtColor(array, cv2.COLOR_RGB2BGR)
    assert cv2.imwrite(str(path), bgr)
    return path


def outputs_for(paths, width, height):
    n = len(paths)
    c2w = np.tile(np.eye(4), (n, 1, 1))
    cameras = make_cameras(c2w, np.tile([50.0, 50.0, width / 2, height / 2], (n, 1)), [width] * n, [height] * n)
    return DataparserOutputs(image_filenames=list(paths), cameras=cameras, split="train")


def test_images_are_uint8_lazy_and_match_the_files(tmp_path):
    rng = np.random.default_rng(0)
    arrays = [rng.integers(0, 256, size=(12, 20, 3), dtype=np.uint8) for _ in range(3)]
    paths = [write_png(tmp_path / f"{i}.png", a) for i, a in enumerate(arrays)]
    dataset = ImageDataset(outputs_for(paths, 20, 12))
    assert len(dataset) == 3 and dataset.num_loaded() == 0
    image = dataset.image_uint8(1)
    assert image.dtype == torch.uint8 and image.shape == (12, 20, 3)
    assert np.array_equal(image.numpy(), arrays[1])  # RGB order, not OpenCV's BGR
    assert dataset.num_loaded() == 1  # only the requested image was decoded
    as_float = dataset.image_float(1)
    assert as_float.dtype == torch.float32
    assert torch.allclose(as_float, torch.from_numpy(arrays[1].astype(np.float32) / 255.0))
    assert dataset[2]["image"].shape == (12, 20, 3) and dataset[-1]["image_idx"] == 2
    with pytest.raises(IndexError, match="out of range"):
        dataset.image_uint8(3)


def test_rgba_keeps_its_alpha_for_the_model_to_composite(tmp_path):
    from kc_splatfacto.losses.layout import composite_with_background

    rng = np.random.default_rng(1)
    rgba = rng.integers(0, 256, size=(8, 10, 4), dtype=np.uint8)
    rgba[0, 0, 3], rgba[0, 1, 3] = 0, 255
    path = write_png(tmp_path / "rgba.png", rgba)
    dataset = ImageDataset(outputs_for([path], 10, 8))
    got = dataset.image_uint8(0)
    assert got.shape == (8, 10, 4) and np.array_equal(got.numpy(), rgba)  # the file's straight alpha, untouched
    assert dataset.mask(0) is None  # alpha is not a mask: it is composited
    background = torch.tensor([0.2, 0.5, 1.0])
    composited = composite_with_background(dataset.image_float(0).double(), background.double()).numpy()
    a = rgba[..., 3:4] / 255.0
    np.testing.assert_allclose(composited, rgba[..., :3] / 255.0 * a + np.array([0.2, 0.5, 1.0]) * (1 - a), atol=1e-7)
    assert np.allclose(composited[0, 0], [0.2, 0.5, 1.0])


def test_gray_and_16_bit_images_become_rgb_uint8(tmp_path):
    gray16 = (np.arange(6 * 7, dtype=np.uint16).reshape(6, 7) * 1500).astype(np.uint16)
    path = tmp_path / "g16.png"
    assert cv2.imwrite(str(path), gray16)
    image = ImageDataset(outputs_for([path], 7, 6)).image_uint8(0).numpy()
    assert image.shape == (6, 7, 3)
    assert np.array_equal(image[..., 0], np.round(gray16 / 257.0).astype(np.uint8))


def test_corrupt_image_is_a_clear_error_naming_the_file(tmp_path):
    path = tmp_path / "broken.jpg"
    path.write_bytes(b"\xff\xd8 this is not a jpeg")
    with pytest.raises(DataParserError, match="broken.jpg.*corrupt"):
        ImageDataset(outputs_for([path], 10, 8)).image_uint8(0)


def test_nan_pixels_in_float_images_are_a_clear_error(tmp_path):
    image = np.full((4, 5, 3), 0.5, np.float32)
    image[1, 2, 0] = np.nan
    path = tmp_path / "nan.tiff"  # float TIFF: a format OpenCV reads back as float32
    assert cv2.imwrite(str(path), image)
    with pytest.raises(DataParserError, match="nan.tiff has 1 NaN"):
        ImageDataset(outputs_for([path], 5, 4)).image_uint8(0)
    finite = tmp_path / "ok.tiff"
    assert cv2.imwrite(str(finite), np.full((4, 5, 3), 0.5, np.float32))
    assert int(ImageDataset(outputs_for([finite], 5, 4)).image_uint8(0)[0, 0, 0]) == 128


def test_image_of_the_wrong_size_for_its_camera_is_an_error(tmp_path):
    path = write_png(tmp_path / "small.png", np.zeros((6, 6, 3), np.uint8))
    with pytest.raises(DataParserError, match="small.png is 6x6 but its camera expects 10x8"):
        ImageDataset(outputs_for([path], 10, 8)).image_uint8(0)
