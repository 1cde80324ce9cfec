"""Careless or hostile scenes (issue 11): each case that used to give a silent wrong result is now an error naming
the file (or a said, correct behaviour), and nothing is written outside the scene's cache or the run folder."""

import json
import os
import shutil
import warnings

import cv2
import numpy as np
import pytest
import torch

from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.colmap import ColmapDataParserConfig, read_colmap_model
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.images import read_image
from kc_splatfacto.data.spars3r import Spars3rDataParserConfig
from kc_splatfacto.data.transforms import TransformsDataParserConfig
from kc_splatfacto.errors import UserError
from tests.data_scenes import scene_variant


def parse(config, split="train"):
    return config.setup().get_dataparser_outputs(split)


def files_under(folder):
    return sorted(str(p) for p in folder.rglob("*"))


# ------------------------------------------------------------------------------------------------ images


@pytest.mark.parametrize("suffix", [".jpg", ".png"])
def test_truncated_image_is_an_error_naming_the_file(tmp_path, suffix):
    """OpenCV decodes a half JPEG with a grey lower half (no error): every incomplete decode must be an error."""
    rng = np.random.default_rng(0)
    image = (rng.random((120, 160, 3)) * 255).astype(np.uint8)
    whole = tmp_path / f"whole{suffix}"
    cv2.imwrite(str(whole), image)
    data = whole.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) // 2])
    assert read_image(whole).shape == (120, 160, 3)
    with pytest.raises(DataParserError, match=f"{cut}.*(truncated|corrupt)"):
        read_image(cut)


def test_truncated_training_image_stops_the_parse_of_a_scene(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene")
    name = (scene / "train_list.txt").read_text().split()[0]
    path = scene / "images" / name
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    outputs = parse(Spars3rDataParserConfig(data=scene))
    index = [p.name for p in outputs.image_filenames].index(name)
    with pytest.raises(DataParserError, match=f"{name}.*truncated"):
        ImageDataset(outputs).image_uint8(index)


# ------------------------------------------------------------------------------------------------ quaternions


def scale_quaternion(target, factor):
    def edit(fields):
        if fields[9] == target:
            fields[1:5] = [repr(float(v) * factor) for v in fields[1:5]]
        return fields

    return edit


@pytest.mark.parametrize("factor", [3.0, 0.0])
def test_far_from_unit_quaternion_is_an_error_naming_image_and_line(castle_p30, tmp_path, factor):
    scene = scene_variant(castle_p30, tmp_path / "scene", edit_image_line=scale_quaternion("0005.jpg", factor))
    images_txt = scene / "sparse" / "0" / "images.txt"
    line = next(i for i, text in enumerate(images_txt.read_text().splitlines(), 1) if text.endswith(" 0005.jpg"))
    with pytest.raises(DataParserError, match=f"images.txt:{line}: .*'0005.jpg' has norm {factor:g}"):
        parse(Spars3rDataParserConfig(data=scene))


def test_nearly_unit_quaternion_is_normalized_to_a_rotation(castle_p30, tmp_path):
    """Within the tolerance (rounding in a text model) the quaternion is normalized: the pose equals the unit one."""
    reference = read_colmap_model(castle_p30 / "sparse" / "0", load_points=False).by_name["0005.jpg"]
    scene = scene_variant(castle_p30, tmp_path / "scene", edit_image_line=scale_quaternion("0005.jpg", 1.0004))
    image = read_colmap_model(scene / "sparse" / "0", load_points=False).by_name["0005.jpg"]
    rotation = image.world_to_camera[:3, :3]
    assert np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)  # a rotation, not a scaled one
    assert np.allclose(image.world_to_camera, reference.world_to_camera, atol=1e-9)


# ------------------------------------------------------------------------------------------------ names escaping


def test_split_list_name_climbing_out_of_the_scene_is_refused(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene")
    (tmp_path / "secret.jpg").write_bytes((scene / "images" / "0000.jpg").read_bytes())
    names = (scene / "train_list.txt").read_text().split()
    (scene / "train_list.txt").write_text("\n".join(["../../secret.jpg", *names[1:]]) + "\n")
    with pytest.raises(DataParserError, match="train_list.txt: '../../secret.jpg' climbs out"):
        parse(Spars3rDataParserConfig(data=scene))


def test_absolute_image_name_in_images_txt_is_refused(castle_p30, tmp_path):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    shutil.copyfile(castle_p30 / "images" / "0000.jpg", outside / "0000.jpg")

    def absolute(fields):
        if fields[9] == "0000.jpg":
            fields[9] = str(outside / "0000.jpg")
        return fields

    scene = scene_variant(castle_p30, tmp_path / "scene", with_lists=False, edit_image_line=absolute)
    with pytest.raises(DataParserError, match=f"images.txt: '{outside / '0000.jpg'}' is an absolute path"):
        parse(ColmapDataParserConfig(data=scene))


def test_symlink_out_of_the_scene_is_refused_and_distorted_cache_stays_inside(castle_p30, tmp_path, monkeypatch):
    """A distorted camera writes undistorted copies under the name's relative path: a name that escapes would write
    outside. Refused before anything is written; a symlinked file is refused too unless allowed explicitly."""
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(tmp_path / "cache"))
    cameras = (castle_p30 / "sparse" / "0" / "cameras.txt").read_text().splitlines()
    fields = next(line for line in cameras if not line.startswith("#")).split()
    fields[1], fields[4:] = "OPENCV", [*fields[4:8], "-0.05", "0.01", "0", "0"]  # PINHOLE -> distorted OPENCV
    outside = tmp_path / "outside"
    outside.mkdir()
    shutil.copyfile(castle_p30 / "images" / "0001.jpg", outside / "0001.jpg")

    def climb(fields):
        if fields[9] == "0001.jpg":
            fields[9] = "../../outside/0001.jpg"
        return fields

    scene = scene_variant(castle_p30, tmp_path / "scene", with_lists=False, cameras_txt=" ".join(fields),
                          edit_image_line=climb)
    before = files_under(tmp_path / "outside")
    with pytest.raises(DataParserError, match="'../../outside/0001.jpg' climbs out"):
        parse(ColmapDataParserConfig(data=scene, eval_mode="all"))
    assert files_under(tmp_path / "outside") == before

    linked = scene_variant(castle_p30, tmp_path / "linked", with_lists=False, cameras_txt=" ".join(fields))
    (linked / "images" / "0001.jpg").unlink()
    (linked / "images" / "0001.jpg").symlink_to(outside / "0001.jpg")
    with pytest.raises(DataParserError, match="'0001.jpg' leads \\(through a symlink\\) to .*outside"):
        parse(ColmapDataParserConfig(data=linked, eval_mode="all"))
    outputs = parse(ColmapDataParserConfig(data=linked, eval_mode="all", allow_symlinks_out=True))
    assert len(outputs.image_filenames) == 24
    assert files_under(tmp_path / "outside") == before  # read, never written


def test_transforms_json_file_path_outside_the_folder_is_refused(tmp_path):
    scene = tmp_path / "ns"
    scene.mkdir()
    cv2.imwrite(str(tmp_path / "private.png"), np.zeros((8, 8, 3), np.uint8))
    frame = {"file_path": "../private.png", "transform_matrix": np.eye(4).tolist()}
    meta = {"fl_x": 10, "fl_y": 10, "cx": 4, "cy": 4, "w": 8, "h": 8, "frames": [frame]}
    (scene / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataParserError, match="transforms.json file_path: '../private.png' climbs out"):
        parse(TransformsDataParserConfig(data=scene))


# ------------------------------------------------------------------------------------------------ duplicates


def test_name_listed_twice_is_an_error_naming_the_lines(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene")
    names = (scene / "train_list.txt").read_text().split()
    (scene / "train_list.txt").write_text("\n".join([*names, names[2]]) + "\n")
    with pytest.raises(DataParserError, match=f"train_list.txt: '{names[2]}' is listed twice \\(lines 3 and 13\\)"):
        parse(Spars3rDataParserConfig(data=scene))


def test_image_registered_twice_in_images_txt_is_an_error(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene", with_lists=False,
                          rename=lambda name: "0000.jpg" if name == "0001.jpg" else name)
    with pytest.raises(DataParserError, match="registers 0000.jpg more than once"):
        parse(ColmapDataParserConfig(data=scene))


def test_transforms_split_list_with_a_duplicate_is_an_error(tmp_path):
    scene = tmp_path / "ns"
    (scene / "images").mkdir(parents=True)
    frames = []
    for i in range(3):
        cv2.imwrite(str(scene / "images" / f"{i}.png"), np.full((8, 8, 3), 40 * i, np.uint8))
        c2w = np.eye(4)
        c2w[0, 3] = i
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": c2w.tolist()})
    meta = {"fl_x": 10, "fl_y": 10, "cx": 4, "cy": 4, "w": 8, "h": 8, "frames": frames,
            "train_filenames": ["images/0.png", "images/1.png", "images/0.png"], "test_filenames": ["images/2.png"]}
    (scene / "transforms.json").write_text(json.dumps(meta))
    with pytest.raises(DataParserError, match="'images/0.png' is listed twice in train_filenames"):
        parse(TransformsDataParserConfig(data=scene))


# ------------------------------------------------------------------------------------------------ points3D


def test_nan_in_points3d_txt_is_dropped_with_a_warning_naming_file_and_lines(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene")
    points_txt = scene / "sparse" / "0" / "points3D.txt"
    lines = points_txt.read_text().splitlines()
    data = [i for i, line in enumerate(lines) if line.strip() and not line.startswith("#")]
    for k, value in ((data[0], "nan"), (data[5], "inf")):
        fields = lines[k].split()
        fields[2] = value
        lines[k] = " ".join(fields)
    points_txt.write_text("\n".join(lines) + "\n")
    with pytest.warns(UserWarning, match=f"points3D.txt: 2 3D points with NaN/inf .*lines {data[0] + 1}, {data[5] + 1}"):
        outputs = parse(Spars3rDataParserConfig(data=scene))
    reference = parse(Spars3rDataParserConfig(data=castle_p30))
    assert outputs.points3d_xyz.shape[0] == reference.points3d_xyz.shape[0] - 2
    assert torch.isfinite(outputs.points3d_xyz).all()


def test_missing_points3d_file_is_named(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene")
    (scene / "sparse" / "0" / "points3D.txt").unlink()
    with pytest.raises(DataParserError, match="sparse/0 has cameras and images but no points3D.bin or points3D.txt"):
        parse(Spars3rDataParserConfig(data=scene))


def test_empty_test_list_is_an_error_naming_it(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene", test_list=[])
    with pytest.raises(DataParserError, match="the test list .*test_list.txt is empty"):
        parse(Spars3rDataParserConfig(data=scene), "train")


def test_data_errors_are_user_errors():
    assert issubclass(DataParserError, UserError) and issubclass(DataParserError, ValueError)


# ------------------------------------------------------------------------------------------------ file modes


def test_atomic_writes_respect_the_umask_like_a_plain_write(tmp_path):
    old = os.umask(0o027)
    try:
        plain = tmp_path / "plain.txt"
        plain.write_text("x")
        atomic = atomic_write_text(tmp_path / "atomic.txt", "x")
        assert (atomic.stat().st_mode & 0o777) == (plain.stat().st_mode & 0o777) == 0o640
        os.umask(0o022)
        atomic_write_text(tmp_path / "new.txt", "x")
        assert (tmp_path / "new.txt").stat().st_mode & 0o777 == 0o644
        (tmp_path / "kept.txt").write_text("x")
        (tmp_path / "kept.txt").chmod(0o600)  # rewriting keeps an existing file's mode, as open(..., "w") does
        atomic_write_text(tmp_path / "kept.txt", "y")
        assert (tmp_path / "kept.txt").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)


def test_no_warnings_for_a_clean_scene(castle_p30):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        parse(Spars3rDataParserConfig(data=castle_p30))
