"""SPARS3R scenes: the paper's sparse protocol (12 train views, test views alternating with them).

Layout::

    <scene>/images/ (or images_train+test/)   train and test images
    <scene>/train_list.txt (or train.txt)      train basenames, one a line
    <scene>/test_list.txt  (or test.txt)       test basenames, one a line
    <scene>/sparse/0/ (or sparse_*/0/)         COLMAP model (.bin or .txt) holding the train and test poses

Train is the train list, eval is the test list; a "val" request gets the test list too (SPARS3R's own fork crashes
there). Test names absent from the model are listed by name in one warning and left out: SPARS3R drops test views it
could not register well. A train name absent from the model, or any listed file absent from the image folder, is an
error. Poses are normalized on the train and test poses together (nerfstudio's COLMAP world, then its defaults).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

from kc_splatfacto.data.base import DataParser, DataParserConfig, DataParserError, read_split_list
from kc_splatfacto.data.colmap import (
    colmap_split_outputs,
    find_model_dir,
    has_model,
    image_folder,
    read_colmap_model,
)
from kc_splatfacto.data.outputs import DataparserOutputs
from kc_splatfacto.data.paths import check_names_inside
from kc_splatfacto.registry import DataParserSpecification

IMAGE_DIR_NAMES = ("images", "images_train+test")
TRAIN_LIST_NAMES = ("train_list.txt", "train.txt")
TEST_LIST_NAMES = ("test_list.txt", "test.txt")


@dataclass
class Spars3rDataParserConfig(DataParserConfig):
    """A SPARS3R-style sparse-view scene (see the module docstring for the layout)."""

    images_path: Path | None = None
    """Image folder relative to ``data``; None tries images/, images_train+test/."""
    colmap_path: Path | None = None
    """Model folder relative to ``data``; None tries sparse/0, then a single sparse_*/0."""
    load_3d_points: bool = True
    """Seed points from points3D."""
    masks_path: Path | None = None
    """Optional mask folder relative to ``data``: ``<masks_path>/<image name>.png``, white = use the pixel."""

    def setup(self) -> Spars3rDataParser:
        return Spars3rDataParser(self)


def find_first(scene: Path, names: tuple[str, ...], what: str, is_dir: bool = False) -> Path:
    for name in names:
        path = scene / name
        if path.is_dir() if is_dir else path.is_file():
            return path
    raise DataParserError(f"{scene} has no {what}: expected one of {', '.join(names)}")


def spars3r_model_dir(scene: Path, configured: Path | None) -> Path:
    """``sparse/0`` when present, else the single ``sparse_*/0`` of SPARS3R's pipeline output."""
    if configured is not None or has_model(scene / "sparse" / "0"):
        return find_model_dir(scene, configured, ("sparse/0",))
    found = sorted(p for p in scene.glob("sparse_*/0") if has_model(p))
    if len(found) == 1:
        return found[0]
    if len(found) > 1:
        raise DataParserError(
            f"{scene} has several COLMAP models ({', '.join(str(p.relative_to(scene)) for p in found)}): "
            "choose one with colmap_path"
        )
    return find_model_dir(scene, None, ("sparse/0",))


def is_spars3r_scene(scene: Path) -> bool:
    """Detection: split lists next to an image folder."""
    return (
        any((scene / n).is_file() for n in TRAIN_LIST_NAMES)
        and any((scene / n).is_file() for n in TEST_LIST_NAMES)
        and any((scene / n).is_dir() for n in IMAGE_DIR_NAMES)
    )


class Spars3rDataParser(DataParser):
    config: Spars3rDataParserConfig
    scene_name = "SPARS3R scene folder"

    def _generate_dataparser_outputs(self, split: str) -> DataparserOutputs:
        scene = Path(self.config.data)
        if self.config.images_path is not None:
            images_dir = image_folder(scene, self.config.images_path)
        else:
            images_dir = find_first(scene, IMAGE_DIR_NAMES, "image folder", is_dir=True)
        train_list = find_first(scene, TRAIN_LIST_NAMES, "train list")
        test_list = find_first(scene, TEST_LIST_NAMES, "test list")
        train_names, test_names = read_split_list(train_list), read_split_list(test_list)
        if not train_names:
            raise DataParserError(f"the train list {train_list} is empty: list the training images, one a line")
        if not test_names:
            raise DataParserError(
                f"the test list {test_list} is empty: list the test images, one a line (evaluation needs at least one)"
            )
        for names, listing in ((train_names, train_list), (test_names, test_list)):
            check_names_inside(images_dir, names, str(listing), self.config.allow_symlinks_out)

        model_dir = spars3r_model_dir(scene, self.config.colmap_path)
        model = self.memo(("colmap", model_dir), read_colmap_model, model_dir, self.config.load_3d_points)
        missing_train = [n for n in train_names if n not in model.by_name]
        if missing_train:
            raise DataParserError(
                f"train images {', '.join(missing_train)} (from {train_list}) have no pose in the COLMAP model "
                f"{model.path}: register them or remove them from the list"
            )
        dropped = [n for n in test_names if n not in model.by_name]
        if dropped:
            warnings.warn(
                f"{len(dropped)} test image(s) from {test_list} are not in the COLMAP model {model.path} and are left "
                f"out: {', '.join(dropped)}", stacklevel=2
            )
        test_names = [n for n in test_names if n in model.by_name]
        overlap = sorted(set(train_names) & set(test_names))
        if overlap:
            warnings.warn(
                f"{train_list} and {test_list} share images {', '.join(overlap)}: they are in both splits",
                stacklevel=2,
            )
        # Normalization on train and test together, each pose once, in list order.
        normalize_names = list(dict.fromkeys(train_names + test_names))
        split_names = train_names if split == "train" else test_names
        if not split_names:
            raise DataParserError(
                f"split '{split}' of {scene} is empty: every name in {test_list} is missing from the COLMAP model"
            )
        return colmap_split_outputs(
            self.config,
            model,
            images_dir,
            normalize_names=normalize_names,
            split_names=split_names,
            split=split,
            load_points=self.config.load_3d_points,
            metadata={"format": "spars3r", "model_dir": model.path, "dropped_test_images": dropped},
        )


def _spec():
    return DataParserSpecification(
        config=Spars3rDataParserConfig(),
        description="SPARS3R sparse-view scene: images/, train_list.txt, test_list.txt, COLMAP sparse/0 or sparse_*/0",
    )


spars3r_dataparser = _spec()
