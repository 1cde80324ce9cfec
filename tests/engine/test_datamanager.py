"""engine/datamanager.py: which scene (the dataparser's ``data``, the one field that holds it), the dataparser it
resolves to, and the order of training views: every image once per epoch, shuffled by python's random.Random(seed)
(checked against an independent shuffle), continued exactly after a checkpoint round trip."""

from __future__ import annotations

import dataclasses
import io
import random
from pathlib import Path

import pytest
import torch

from kc_splatfacto.data.base import DataParserError
from kc_splatfacto.data.demo import DemoDataParserConfig
from kc_splatfacto.data.detect import AutoDataParserConfig
from kc_splatfacto.data.spars3r import Spars3rDataParserConfig
from kc_splatfacto.engine.datamanager import DataManager, DataManagerConfig

SIZE = dict(width=32, height=24, num_cameras=8, num_points=200)


def demo_manager(tmp_path, seed=0) -> DataManager:
    config = DataManagerConfig(dataparser=DemoDataParserConfig(**SIZE, demo_cache_dir=tmp_path / "demo-cache"))
    return config.setup(seed=seed)


def expected_order(seed: int, n: int, epochs: int) -> list[int]:
    """The draw order written out: each epoch a fresh shuffle of range(n) by one random.Random(seed)."""
    rng = random.Random(seed)
    order = []
    for _ in range(epochs):
        epoch = list(range(n))
        rng.shuffle(epoch)
        order += epoch
    return order


@pytest.mark.parametrize("seed", [0, 7])
def test_every_training_view_once_per_epoch_in_the_seeds_shuffle(tmp_path, seed):
    manager = demo_manager(tmp_path, seed)
    n = len(manager.train_dataset)
    drawn = [manager.next_train()["image_idx"] for _ in range(3 * n)]
    assert drawn == expected_order(seed, n, 3)
    for epoch in range(3):
        assert sorted(drawn[epoch * n:(epoch + 1) * n]) == list(range(n))


def test_a_batch_holds_the_view_its_index_names(tmp_path):
    manager = demo_manager(tmp_path)
    batch = manager.next_train()
    index = batch["image_idx"]
    assert torch.equal(batch["image"], manager.train_dataset[index]["image"])
    assert batch["image"].dtype == torch.uint8 and batch["image"].shape[-1] == 3
    assert torch.equal(batch["camera"].viewmats, manager.train_dataset.cameras[index].viewmats)


def test_the_order_continues_exactly_after_a_weights_only_round_trip_mid_epoch(tmp_path):
    manager = demo_manager(tmp_path, seed=4)
    for _ in range(3):
        manager.next_train()
    buffer = io.BytesIO()
    torch.save(manager.state_dict(), buffer)  # python's random state becomes lists: the round trip must undo it
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)
    upcoming = [manager.next_train()["image_idx"] for _ in range(12)]
    restored = demo_manager(tmp_path, seed=99)
    restored.load_state_dict(state)
    assert [restored.next_train()["image_idx"] for _ in range(12)] == upcoming


def test_the_scene_is_the_dataparsers_data_alone(tmp_path, castle_p30):
    config = DataManagerConfig()
    assert not any(f.name == "data" for f in dataclasses.fields(config))
    config.set_scene(castle_p30)
    assert config.scene == castle_p30 == config.dataparser.data
    resolved = config.resolve_dataparser()  # auto: detected from the scene
    assert type(resolved) is Spars3rDataParserConfig and resolved.data == castle_p30
    assert isinstance(config.dataparser, AutoDataParserConfig)  # left as given
    explicit = DataManagerConfig(dataparser=Spars3rDataParserConfig(data=castle_p30))
    copy_ = explicit.resolve_dataparser()
    assert copy_ == explicit.dataparser and copy_ is not explicit.dataparser


def test_an_earlier_config_files_scene_field_moves_into_the_dataparser():
    fields = {"data": Path("/somewhere"), "dataparser": AutoDataParserConfig(), "eval_split": "test"}
    upgraded = DataManagerConfig.upgrade_fields(dict(fields))
    assert "data" not in upgraded and upgraded["dataparser"].data == Path("/somewhere")
    empty = DataManagerConfig.upgrade_fields({"data": None, "dataparser": AutoDataParserConfig()})
    assert empty["dataparser"].data == AutoDataParserConfig().data  # an empty field, as every run wrote it


def test_an_empty_train_split_is_a_clear_error(tmp_path, monkeypatch):
    from kc_splatfacto.engine import datamanager as module

    monkeypatch.setattr(module, "ImageDataset", lambda outputs: [])
    with pytest.raises(DataParserError, match="train split of .* is empty"):
        demo_manager(tmp_path)
