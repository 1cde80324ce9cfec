"""Full-image data manager (nerfstudio's ``FullImageDatamanager``): one training image per step, each image once per
epoch in a shuffled order, images kept as uint8 and made float by the model per step.
"""

from __future__ import annotations

import dataclasses
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
import tyro

from kc_splatfacto.data.base import DataParserConfig, DataParserError, write_dataparser_transforms
from kc_splatfacto.data.dataset import ImageDataset
from kc_splatfacto.data.detect import AutoDataParserConfig
from kc_splatfacto.engine.checkpoints import as_random_state
from kc_splatfacto.registry import discover_dataparsers

#: the ``dataparser`` field's annotation: any dataparser config until a command line installs one subcommand per
#: registered dataparser (:func:`install_dataparser_subcommands`), so importing this module discovers nothing (a broken
#: third-party plugin then fails the command that lists the dataparsers, not every import of the engine)
DataParserUnion: Any = DataParserConfig


def dataparser_subcommands() -> Any:
    """The ``dataparser`` field's type on a command line: one tyro subcommand per registered dataparser, plus ``auto``
    (detect the format from ``--data``), without the ``pipeline.datamanager.dataparser`` prefix (nerfstudio's
    ``AnnotatedDataParserUnion``): ``kc-train kc-splatfacto --data SCENE colmap --downscale-factor 4``."""
    specs = discover_dataparsers()
    defaults = {"auto": AutoDataParserConfig(), **{name: spec.config for name, spec in specs.items()}}
    descriptions = {"auto": "detect the format from --data (the default)",
                    **{name: spec.description for name, spec in specs.items()}}
    union = tyro.extras.subcommand_type_from_defaults(defaults, descriptions, prefix_names=False)
    return tyro.conf.OmitSubcommandPrefixes[union]  # type: ignore[misc,valid-type]  # a type built at run time


def install_dataparser_subcommands() -> None:
    """Make the ``dataparser`` field's annotation the registered dataparsers' subcommands (discovered now): what a
    command line does before tyro reads ``DataManagerConfig``'s fields."""
    global DataParserUnion
    DataParserUnion = dataparser_subcommands()


@dataclass
class DataManagerConfig:
    """Which scene to load and how; ``setup()`` builds the :class:`DataManager`."""

    dataparser: DataParserUnion = field(default_factory=AutoDataParserConfig)
    """the dataparser config: a subcommand after the method's options (default: auto, detected from its ``data``, the
    scene: the one field that holds the scene path; ``kc-train ... --data SCENE`` sets it)"""
    eval_split: Literal["test", "val", "train"] = "test"
    """split evaluated during and after training"""

    @property
    def scene(self) -> Path:
        """The scene the dataparser reads (its ``data``)."""
        return Path(self.dataparser.data)

    def set_scene(self, data: Path | str) -> None:
        """Read the scene at ``data`` (a folder, or 'demo'): sets the dataparser's ``data``."""
        self.dataparser = dataclasses.replace(self.dataparser, data=Path(data))

    def resolve_dataparser(self) -> DataParserConfig:
        """The concrete dataparser config to use: the given one, with ``auto`` detected from the scene.

        Returns a new config; this one is left as the user wrote it.
        """
        if isinstance(self.dataparser, AutoDataParserConfig):
            return self.dataparser.resolve()
        return dataclasses.replace(self.dataparser)

    @classmethod
    def upgrade_fields(cls, fields: dict[str, Any]) -> dict[str, Any]:
        """A ``config.yml`` of an earlier version had a ``data`` field here (always empty in the files runs wrote):
        the scene is the dataparser's ``data``."""
        data = fields.pop("data", None)
        if data is not None and "dataparser" in fields:
            fields["dataparser"] = dataclasses.replace(fields["dataparser"], data=Path(data))
        return fields

    def setup(self, seed: int = 42, dataparser: DataParserConfig | None = None) -> DataManager:
        """The :class:`DataManager`; ``dataparser`` is the resolved dataparser config when the caller has it (a
        planned run: :func:`kc_splatfacto.engine.run_guard.plan_run`), else :meth:`resolve_dataparser`."""
        return DataManager(self, seed=seed, dataparser=dataparser)


class DataManager:
    """Loads the train and eval splits of one scene and hands out training batches.

    Attributes:
        dataparser_config: the resolved dataparser config it loaded (what ``config.yml`` records to rebuild the run).
        train_dataset, eval_dataset: the two splits as :class:`ImageDataset`.
    """

    def __init__(self, config: DataManagerConfig, seed: int = 42, dataparser: DataParserConfig | None = None):
        self.config = config
        self.dataparser_config = dataparser if dataparser is not None else config.resolve_dataparser()
        self.dataparser = self.dataparser_config.setup()
        self.train_outputs = self.dataparser.get_dataparser_outputs(split="train")
        self.eval_outputs = self.dataparser.get_dataparser_outputs(split=config.eval_split)
        self.train_dataset = ImageDataset(self.train_outputs)
        self.eval_dataset = ImageDataset(self.eval_outputs)
        if len(self.train_dataset) == 0:
            raise DataParserError(f"the train split of {self.dataparser_config.data} is empty: a scene needs at least one "
                             "training image")
        self._rng = random.Random(seed)
        self._unseen: list[int] = []

    def seed_points(self) -> tuple[torch.Tensor, torch.Tensor | None] | None:
        xyz = self.train_outputs.points3d_xyz
        if xyz is None or len(xyz) == 0:
            return None
        return torch.as_tensor(xyz).float(), self.train_outputs.points3d_rgb

    def next_train(self) -> dict[str, Any]:
        """The next training batch: ``image_idx`` (int), ``camera`` (Cameras of length 1), ``image`` [H, W, 3|4]
        uint8 (RGBA keeps its alpha: the model composites it over its background) and ``mask`` [H, W, 1] bool when
        the scene has masks."""
        if not self._unseen:
            self._unseen = list(range(len(self.train_dataset)))
            self._rng.shuffle(self._unseen)
        index = self._unseen.pop(0)
        return {**self.train_dataset[index], "camera": self.train_dataset.cameras[index]}

    def state_dict(self) -> dict[str, Any]:
        return {"rng": self._rng.getstate(), "unseen": list(self._unseen)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self._rng.setstate(as_random_state(state["rng"]))
        self._unseen = list(state["unseen"])

    def save_dataparser_transform(self, path: Path) -> None:
        """``dataparser_transforms.json`` as nerfstudio writes it: ``transform`` [3, 4] and ``scale``."""
        write_dataparser_transforms(path, self.train_outputs)
