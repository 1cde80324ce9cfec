"""Bad scene input: each case is a clear DataParserError naming the file or argument and the fix."""

import re
from pathlib import Path

import cv2
import numpy as np
import pytest

from kc_splatfacto.data import resolve_dataparser
from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.colmap import ColmapDataParserConfig
from kc_splatfacto.data.spars3r import Spars3rDataParserConfig
from kc_splatfacto.data.transforms import TransformsDataParserConfig
from kc_splatfacto.registry import DataParserSpecification
from tests.data_scenes import scene_variant

custom_parser = DataParserSpecification(config=ColmapDataParserConfig(eval_mode="all"), description="a third-party one")


def parse(config, split="train"):
    return config.setup().get_dataparser_outputs(split)


def test_missing_scene_folder(tmp_path):
    with pytest.raises(DataParserError, match="nowhere.*does not exist"):
        resolve_dataparser(tmp_path / "nowhere")
    with pytest.raises(DataParserError, match="nowhere does not exist"):
        parse(Spars3rDataParserConfig(data=tmp_path / "nowhere"))
    with pytest.raises(DataParserError, match="nowhere does not exist"):
        parse(ColmapDataParserConfig(data=tmp_path / "nowhere"))


@pytest.mark.parametrize(
    "config_type, name, may_be_file",
    [(ColmapDataParserConfig, "COLMAP scene folder", False), (Spars3rDataParserConfig, "SPARS3R scene folder", False),
     (TransformsDataParserConfig, "scene", True)],
)
def test_the_scene_check_is_the_base_class_one(tmp_path, config_type, name, may_be_file):
    """One check for every parser (DataParser.check_scene), before the split's outputs are built: the parser's name
    for the scene, and a file refused where the format needs a folder."""
    with pytest.raises(DataParserError, match=f"^{name} {tmp_path / 'nowhere'} does not exist: check --data$"):
        parse(config_type(data=tmp_path / "nowhere"), "test")
    a_file = tmp_path / "scene.json"
    a_file.write_text("{}")
    if may_be_file:  # the file itself is read (and found wanting), not refused as a file
        with pytest.raises(DataParserError, match="has no 'frames' list"):
            parse(config_type(data=a_file))
    else:
        with pytest.raises(DataParserError, match=f"^{name} {a_file} is not a folder: check --data$"):
            parse(config_type(data=a_file))


@pytest.mark.parametrize("config_type", [ColmapDataParserConfig, Spars3rDataParserConfig])
def test_a_configured_image_folder_must_be_a_folder(castle_p30, config_type):
    with pytest.raises(DataParserError, match="image folder .*pictures does not exist: set images_path to the scene"):
        parse(config_type(data=castle_p30, images_path=Path("pictures")))


def test_folder_of_unknown_format_says_what_was_expected(tmp_path):
    (tmp_path / "images").mkdir()
    with pytest.raises(DataParserError, match="cannot tell the format.*subcommand") as caught:
        resolve_dataparser(tmp_path)
    # the hint's command is one kc-train really parses, and its subcommand really forces the parser
    command = re.search(r"`kc-train ([^`]*)`", str(caught.value)).group(1).split()
    from kc_splatfacto.cli.train import parse_config

    config = parse_config([str(tmp_path) if word == "SCENE" else word for word in command])
    assert type(config.pipeline.datamanager.dataparser).__name__ == "ColmapDataParserConfig"


def test_missing_model(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene")
    for f in (scene / "sparse" / "0").iterdir():
        f.unlink()
    with pytest.raises(DataParserError, match="no COLMAP model.*sparse/0"):
        parse(Spars3rDataParserConfig(data=scene))
    with pytest.raises(DataParserError, match="no COLMAP model"):
        parse(ColmapDataParserConfig(data=scene))


def test_split_list_naming_an_image_that_does_not_exist(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene", drop_image_files=("0005.jpg",))
    with pytest.raises(DataParserError, match="missing from .*images: 0005.jpg"):
        parse(Spars3rDataParserConfig(data=scene))
    test = parse(Spars3rDataParserConfig(data=scene), "test")  # the other split does not need the file
    assert len(test.image_filenames) == 12


def test_empty_split(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "empty_train", train_list=[])
    with pytest.raises(DataParserError, match="train list .*train_list.txt is empty"):
        parse(Spars3rDataParserConfig(data=scene))
    test_names = (castle_p30 / "test_list.txt").read_text().split()
    scene = scene_variant(castle_p30, tmp_path / "no_tests", drop_model_images=tuple(test_names))
    with pytest.warns(UserWarning, match="left out"), pytest.raises(DataParserError, match="split 'test' .* is empty"):
        parse(Spars3rDataParserConfig(data=scene), "test")
    with pytest.raises(DataParserError, match="split 'test' .* is empty"):  # interval larger than the scene
        parse(ColmapDataParserConfig(data=scene, eval_mode="fraction", train_split_fraction=1.0), "test")


def test_corrupt_image_file(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene", drop_image_files=("0008.jpg",))
    (scene / "images" / "0008.jpg").write_bytes(b"\xff\xd8\xff\xe0 truncated")
    with pytest.raises(DataParserError, match="0008.jpg is corrupt"):
        parse(Spars3rDataParserConfig(data=scene))


def test_images_of_different_sizes_for_one_camera(castle_p30, tmp_path):
    scene = scene_variant(castle_p30, tmp_path / "scene", drop_image_files=("0010.jpg",))
    small = cv2.resize(cv2.imread(str(castle_p30 / "images" / "0010.jpg")), (384, 256))
    cv2.imwrite(str(scene / "images" / "0010.jpg"), small)
    with pytest.raises(DataParserError, match="0010.jpg is 384x256 but its COLMAP camera 1 is 768x512"):
        parse(Spars3rDataParserConfig(data=scene))


def test_nan_in_a_pose(castle_p30, tmp_path):
    def poison(fields):
        if fields[9] == "0013.jpg":
            fields[5] = "nan"
        return fields

    scene = scene_variant(castle_p30, tmp_path / "text", edit_image_line=poison)  # pycolmap cannot parse it
    with pytest.raises(DataParserError, match="images 0013.jpg in .*images.txt contain NaN"):
        parse(Spars3rDataParserConfig(data=scene))
    # a binary model does carry the NaN through pycolmap: the parser's own check names the image
    pycolmap = pytest.importorskip("pycolmap")
    scene = scene_variant(castle_p30, tmp_path / "binary")
    reconstruction = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    image = next(im for im in reconstruction.images.values() if im.name == "0013.jpg")
    frame = reconstruction.frames[image.frame_id]
    pose = frame.rig_from_world
    pose.translation = np.array([np.nan, 0.0, 0.0])
    frame.rig_from_world = pose
    for f in (scene / "sparse" / "0").iterdir():
        f.unlink()
    reconstruction.write_binary(str(scene / "sparse" / "0"))
    with pytest.raises(DataParserError, match="pose of image '0013.jpg' .* contains NaN"):
        parse(Spars3rDataParserConfig(data=scene))


def test_unknown_split_downscale_and_names(castle_p30, monkeypatch):
    with pytest.raises(DataParserError, match="unknown split 'training'"):
        parse(Spars3rDataParserConfig(data=castle_p30), "training")
    with pytest.raises(DataParserError, match="downscale_factor must be an integer >= 1, got 0"):
        Spars3rDataParserConfig(data=castle_p30, downscale_factor=0).setup()
    with pytest.raises(DataParserError, match="unknown dataparser 'blender'.*colmap"):
        resolve_dataparser(castle_p30, "blender")
    with pytest.raises(DataParserError, match="unknown eval_mode 'random'"):
        parse(ColmapDataParserConfig(data=castle_p30, eval_mode="random"))


def test_forced_and_third_party_dataparsers(castle_p30, monkeypatch):
    forced = resolve_dataparser(castle_p30, "colmap")  # detection would say spars3r
    assert isinstance(forced, ColmapDataParserConfig) and forced.data == castle_p30
    assert len(parse(forced).image_filenames) == 21  # interval split of all 24 images
    monkeypatch.setenv("KC_SPLATFACTO_DATAPARSER_CONFIGS", "mine=tests.data.test_bad_input:custom_parser")
    mine = resolve_dataparser(castle_p30, "mine")
    assert mine is not custom_parser.config and mine.data == castle_p30  # a copy: the registry stays pristine
    assert len(parse(mine).image_filenames) == 24


def test_configs_are_plain_dataclasses_that_round_trip_through_yaml(castle_p30):
    import dataclasses

    import yaml

    for name in ("spars3r", "colmap", "nerfstudio-data", "demo"):
        config = resolve_dataparser(castle_p30 if name != "demo" else "demo", name)
        assert dataclasses.is_dataclass(config)
        rebuilt = yaml.unsafe_load(yaml.dump(config))
        assert rebuilt == config
        fields = {f.name: getattr(config, f.name) for f in dataclasses.fields(config)}
        assert type(config)(**fields) == config
        assert set(fields) >= {"data", "downscale_factor"}
