"""Atomic writes: the old file survives a failed write, no temp file is left, a good write replaces it."""

import json

import pytest
import torch

from kc_splatfacto.atomic import atomic_write, atomic_write_bytes, atomic_write_text
from kc_splatfacto.engine.checkpoints import save_checkpoint


def test_good_writes_replace_and_leave_no_temp_files(tmp_path):
    path = tmp_path / "sub" / "a.json"  # the folder is created
    atomic_write_text(path, json.dumps({"v": 1}))
    atomic_write_bytes(path, json.dumps({"v": 2}).encode())
    assert json.loads(path.read_text()) == {"v": 2}
    assert sorted(p.name for p in path.parent.iterdir()) == ["a.json"]


@pytest.mark.parametrize("error", [RuntimeError("disk full"), KeyboardInterrupt()])
def test_failed_write_keeps_the_old_file_and_removes_the_temp_file(tmp_path, error):
    path = tmp_path / "config.yml"
    path.write_text("old")

    def half_then_fail(tmp):
        tmp.write_text("half writ")
        raise error

    with pytest.raises(type(error)):
        atomic_write(path, half_then_fail)
    assert path.read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.yml"]


def test_checkpoint_interrupted_mid_save_keeps_the_previous_checkpoint(tmp_path, monkeypatch):
    first = save_checkpoint(tmp_path, 100, {"step": 100, "w": torch.ones(3)})
    real_save = torch.save

    def interrupted_save(obj, f, *args, **kwargs):
        real_save(obj, f, *args, **kwargs)
        raise KeyboardInterrupt  # Ctrl-C after the bytes, before the rename

    monkeypatch.setattr(torch, "save", interrupted_save)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path, 100, {"step": 100, "w": torch.zeros(3)})
    monkeypatch.undo()
    assert torch.load(first)["w"].tolist() == [1.0, 1.0, 1.0]
    assert sorted(p.name for p in tmp_path.iterdir()) == [first.name]
