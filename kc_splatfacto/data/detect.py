"""Which dataparser reads a scene: detection from the folder (the ``auto`` subcommand, the default), or a registered
dataparser chosen by its subcommand name (``kc-train METHOD --data SCENE colmap ...``)."""

from __future__ import annotations

import copy
import dataclasses
from dataclasses import dataclass
from pathlib import Path

from kc_splatfacto.data.base import DataParser, DataParserConfig, DataParserError
from kc_splatfacto.data.colmap import DEFAULT_MODEL_DIRS, has_model
from kc_splatfacto.data.spars3r import is_spars3r_scene
from kc_splatfacto.registry import discover_dataparsers

DEMO_NAME = "demo"


def detect_format(data: Path) -> str:
    """Registered dataparser name for the scene at ``data``: "spars3r", "nerfstudio-data" or "colmap".

    Order: split lists + image folder (SPARS3R), then a transforms.json (nerfstudio), then a COLMAP model.
    """
    if not data.exists():
        raise DataParserError(f"scene {data} does not exist: give a scene folder, a transforms.json, or 'demo'")
    if data.is_file():
        if data.suffix == ".json":
            return "nerfstudio-data"
        raise DataParserError(f"{data} is a file: give the scene folder (or a transforms.json)")
    if is_spars3r_scene(data):
        return "spars3r"
    if (data / "transforms.json").is_file():
        return "nerfstudio-data"
    if any(has_model(data / d) for d in DEFAULT_MODEL_DIRS) and (data / "images").is_dir():
        return "colmap"
    raise DataParserError(
        f"cannot tell the format of {data}: expected train_list.txt + test_list.txt + images/ (SPARS3R), "
        f"transforms.json (nerfstudio), or images/ + sparse/0/ (COLMAP); or name the dataparser as a subcommand "
        f"after the method's options (`kc-train kc-splatfacto --data SCENE colmap`; registered: "
        f"{', '.join(discover_dataparsers())})"
    )


def resolve_dataparser(data: str | Path, name: str | None = None) -> DataParserConfig:
    """The dataparser config for ``data``: forced by ``name`` (a registered dataparser) or detected.

    ``data == "demo"`` (when no such folder exists) gives the generated demo scene.
    """
    specs = discover_dataparsers()
    path = Path(data)
    if name is None:
        name = DEMO_NAME if str(data) == DEMO_NAME and not path.is_dir() else detect_format(path)
    if name not in specs:
        raise DataParserError(
            f"unknown dataparser '{name}': registered ones are {', '.join(specs) or 'none'} "
            "(is the package installed with `pip install -e .`?)"
        )
    config = copy.deepcopy(specs[name].config)
    if name != DEMO_NAME:
        config.data = path
    return config


@dataclass
class AutoDataParserConfig(DataParserConfig):
    """The dataparser detected from ``data`` (SPARS3R, transforms.json, COLMAP, or 'demo'), with this config's common
    options (downscale, orientation, centring, scaling, cache folder) handed to it: the default subcommand."""

    def resolve(self) -> DataParserConfig:
        """The detected dataparser's config, carrying the common options set here."""
        config = resolve_dataparser(self.data)
        common = {f.name: getattr(self, f.name) for f in dataclasses.fields(DataParserConfig) if f.name != "data"}
        return dataclasses.replace(config, **common)

    def setup(self) -> DataParser:
        return self.resolve().setup()
