"""COLMAP model files checked before pycolmap (issue 26): binary models cut at every record boundary name the file
and what is cut; a text model's errors name file and line; geometry that may be wrong is a warning with counts."""

import struct
import warnings

import numpy as np
import pytest

from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.colmap import SUPPORTED_CAMERA_MODELS, ColmapCamera, check_principal_point, read_colmap_model
from kc_splatfacto.data.colmap_files import COLMAP_CAMERA_MODELS, check_model_files
from tests.hostile_scenes import NUM_VIEWS, colmap_scene


@pytest.fixture(scope="module")
def binary_model(tmp_path_factory):
    return colmap_scene(tmp_path_factory.mktemp("bin") / "scene", binary=True) / "sparse" / "0"


@pytest.fixture(scope="module")
def text_model(tmp_path_factory):
    return colmap_scene(tmp_path_factory.mktemp("txt") / "scene") / "sparse" / "0"


def test_the_tiny_models_read_as_written(binary_model, text_model):
    for model_dir in (binary_model, text_model):
        check_model_files(model_dir, SUPPORTED_CAMERA_MODELS)
        model = read_colmap_model(model_dir)
        assert len(model.images) == NUM_VIEWS and len(model.points_xyz) == 200


@pytest.mark.parametrize("name", ["cameras", "images", "points3D"])
def test_a_binary_file_cut_anywhere_is_named_not_left_to_pycolmap(binary_model, tmp_path, name):
    data = (binary_model / f"{name}.bin").read_bytes()
    cuts = sorted({1, 7, 8, 9, len(data) // 3, len(data) // 2, len(data) - 1})
    for cut in cuts:
        model = tmp_path / f"cut{cut}"
        model.mkdir()
        for other in binary_model.iterdir():
            (model / other.name).write_bytes(other.read_bytes())
        (model / f"{name}.bin").write_bytes(data[:cut])
        with pytest.raises(DataParserError, match=f"{name}.bin is truncated"):
            read_colmap_model(model)


def test_trailing_bytes_after_the_last_record_are_damage(binary_model, tmp_path):
    for other in binary_model.iterdir():
        (tmp_path / other.name).write_bytes(other.read_bytes())
    (tmp_path / "images.bin").write_bytes((binary_model / "images.bin").read_bytes() + b"\0" * 5)
    with pytest.raises(DataParserError, match="images.bin has 5 bytes after its last record"):
        read_colmap_model(tmp_path)


def test_binary_image_with_an_unknown_camera_is_named(binary_model, tmp_path):
    for other in binary_model.iterdir():
        (tmp_path / other.name).write_bytes(other.read_bytes())
    data = bytearray((binary_model / "images.bin").read_bytes())
    struct.pack_into("<I", data, 8 + 4 + 56, 7)  # the first image's camera id
    (tmp_path / "images.bin").write_bytes(bytes(data))
    with pytest.raises(DataParserError, match="images.bin: image '0000.png' names camera 7, which cameras.bin"):
        read_colmap_model(tmp_path)


@pytest.mark.parametrize("model", sorted(set(COLMAP_CAMERA_MODELS) - set(SUPPORTED_CAMERA_MODELS)))
def test_every_unsupported_model_lists_the_supported_ones(text_model, tmp_path, model):
    for other in text_model.iterdir():
        (tmp_path / other.name).write_text(other.read_text())
    params = " ".join(["40"] * COLMAP_CAMERA_MODELS[model][1])
    (tmp_path / "cameras.txt").write_text(f"1 {model} 48 32 {params}\n")
    with pytest.raises(DataParserError) as info:
        read_colmap_model(tmp_path)
    message = str(info.value)
    assert "cameras.txt:1" in message and model in message
    assert all(name in message for name in SUPPORTED_CAMERA_MODELS)


def camera(cx, cy):
    return ColmapCamera("PINHOLE", 48, 32, 40.0, 40.0, cx, cy, np.zeros(5))


def test_principal_point_outside_the_image_warns_and_far_outside_is_refused():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_principal_point(camera(24, 16), "c")
        check_principal_point(camera(0, 32), "c")
    with pytest.warns(UserWarning, match=r"principal point \(-5, 16\) is outside the 48x32 image"):
        check_principal_point(camera(-5, 16), "c")
    for cx, cy in ((-49, 16), (97, 16), (24, -33), (24, 65)):
        with pytest.raises(DataParserError, match="by more than the image's size"):
            check_principal_point(camera(cx, cy), "c")


def test_seed_points_behind_every_camera_are_counted_in_a_warning(text_model, tmp_path):
    for other in text_model.iterdir():
        (tmp_path / other.name).write_text(other.read_text())
    lines = (tmp_path / "points3D.txt").read_text().splitlines()
    moved = []
    for i, line in enumerate(lines):
        fields = line.split()
        if line.startswith("#") or i > 150:
            moved.append(line)
            continue
        fields[1:4] = ["0", "0", "50"]  # far above the cameras, which look at the origin nearly horizontally
        moved.append(" ".join(fields))
    (tmp_path / "points3D.txt").write_text("\n".join(moved) + "\n")
    model = read_colmap_model(text_model)  # the unedited model: no warning
    w2c = np.stack([image.world_to_camera for image in model.images])
    z_up = w2c[:, 2, :3] @ np.array([0, 0, 50.0]) + w2c[:, 2, 3]
    assert (z_up <= 0).all()  # the oracle: a point at (0, 0, 50) is behind each camera
    with pytest.warns(UserWarning, match=r"150 of 200 seed points are behind every camera"):
        read_colmap_model(tmp_path)
