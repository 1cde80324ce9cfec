"""Full-image data manager (nerfstudio's ``FullImageDatamanager``): one training image per step, each image once per
epoch in a shuffled order, images kept as uint8 and made float by the model per step.
"""

from __future__ import annotations

import dataclasses
import random
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import tyro

from kc_splatfacto.data.base import write_dataparser_transforms
from kc_splatfacto.data.dataset import ImageDataset


@dataclass
class DataManagerConfig:
    """Which scene to load and how; ``setup()`` builds the :class:`DataManager`."""

    data: Path | None = None
    """scene folder, or 'demo' for the generated demo scene"""
    dataparser: tyro.conf.Suppress[Any] = None
    """a dataparser config (detected from ``data`` when None)"""
    dataparser_name: str | None = None
    """force a registered dataparser by name instead of detecting the format"""
    downscale_factor: int | None = None
    """image downscale factor handed to the dataparser (None keeps the dataparser's own)"""
    eval_split: str = "test"
    """split evaluated during and after training"""

    def resolve_dataparser(self) -> Any:
        """The dataparser config to use: the explicit one, else detected from ``data``; downscale applied.

        Returns a new config; this one is left as the user wrote it.
        """
        parser_config = self.dataparser
        if parser_config is None:
            if self.data is None:
                raise ValueError("no scene given: pass --data PATH (a scene folder, or 'demo' for the demo scene)")
            from kc_splatfacto.data import resolve_dataparser

            parser_config = resolve_dataparser(self.data, self.dataparser_name)
        if self.downscale_factor is not None and dataclasses.is_dataclass(parser_config):
            parser_config = dataclasses.replace(parser_config, downscale_factor=self.downscale_factor)
        return parser_config

    def setup(self, seed: int = 42) -> DataManager:
        return DataManager(self, seed=seed)


class DataManager:
    """Loads the train and eval splits of one scene and hands out training batches.

    Attributes:
        dataparser_config: the resolved dataparser config (what ``config.yml`` records to rebuild the run).
        train_dataset, eval_dataset: the two splits as :class:`ImageDataset`.
    """

    def __init__(self, config: DataManagerConfig, seed: int = 42):
        self.config = config
        self.dataparser_config = config.resolve_dataparser()
        self.dataparser = self.dataparser_config.setup()
        self.train_outputs = self.dataparser.get_dataparser_outputs(split="train")
        self.eval_outputs = self.dataparser.get_dataparser_outputs(split=config.eval_split)
        self.train_dataset = ImageDataset(self.train_outputs)
        self.eval_dataset = ImageDataset(self.eval_outputs)
        if len(self.train_dataset) == 0:
            raise ValueError(f"the train split of {config.data} is empty: a scene needs at least one training image")
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
        self._rng.setstate(_as_random_state(state["rng"]))
        self._unseen = list(state["unseen"])

    def save_dataparser_transform(self, path: Path) -> None:
        """``dataparser_transforms.json`` as nerfstudio writes it: ``transform`` [3, 4] and ``scale``."""
        write_dataparser_transforms(path, self.train_outputs)


def _as_random_state(state: Any) -> tuple:
    """python's random state after a round trip through a checkpoint (lists instead of tuples)."""
    version, internal, gauss = state
    return (version, tuple(internal), gauss)
