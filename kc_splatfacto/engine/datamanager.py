"""Full-image data manager (nerfstudio's ``FullImageDatamanager``): one training image per step, each image once per
epoch in a shuffled order, images kept as uint8 and made float by the model per step."""

from __future__ import annotations

import random
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from kc_splatfacto.data.base import write_dataparser_transforms

if TYPE_CHECKING:
    from kc_splatfacto.engine.config import DataManagerConfig


class DataManager:
    """Loads the train and eval splits of one scene and hands out training views."""

    def __init__(self, config: "DataManagerConfig", seed: int = 42):
        from kc_splatfacto.data.dataset import ImageDataset

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

    @property
    def test_dataset(self):
        return self.eval_dataset

    def seed_points(self) -> tuple[torch.Tensor, torch.Tensor | None] | None:
        xyz = self.train_outputs.points3d_xyz
        if xyz is None or len(xyz) == 0:
            return None
        return torch.as_tensor(xyz).float(), self.train_outputs.points3d_rgb

    def next_train(self) -> tuple[int, Any, torch.Tensor]:
        """(image index, its Cameras of length 1, its [H, W, 3] uint8 image)."""
        if not self._unseen:
            self._unseen = list(range(len(self.train_dataset)))
            self._rng.shuffle(self._unseen)
        index = self._unseen.pop(0)
        return index, self.train_dataset.cameras[index], self.train_dataset.image_uint8(index)

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
