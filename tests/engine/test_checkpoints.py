"""engine/checkpoints.py: atomic writes and what a crash leaves, save_only_latest, finding a checkpoint by step,
weights-only loading, and check_checkpoint_fits naming the fix.

Tested elsewhere and not repeated here: a Ctrl-C after the bytes keeps the previous checkpoint (tests/test_atomic.py),
an unpicklable payload leaves no file (tests/engine/test_trainer.py), a Path.touch payload, truncated and garbage
files, a full disk, and --load-dir naming a checkpoint file (tests/engine/test_run_guard.py)."""

from __future__ import annotations

import copy
import errno
import os
import random
import shutil
import stat
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from kc_splatfacto.engine.checkpoints import (
    CHECKPOINT_DIR,
    TEMP_PATTERN,
    CheckpointNotFoundError,
    check_checkpoint_fits,
    checkpoint_name,
    checkpoint_step,
    find_checkpoint,
    list_checkpoints,
    load_checkpoint,
    remove_orphan_temp_files,
    save_checkpoint,
)
from kc_splatfacto.engine.optimizers import OptimizersConfig
from kc_splatfacto.errors import CheckpointError
from kc_splatfacto.registry import discover_methods

#: SH coefficients per colour beyond the DC term, for SH degree 0..3 (1, 4, 9, 16 in all)
SH_REST = {0: 0, 1: 3, 2: 8, 3: 15}


def payload(step: int, value: float = 1.0) -> dict:
    return {"step": step, "model": {"means": torch.full((2, 3), value)}}


def names(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir())


# ------------------------------------------------------------------------------------------------ names and listing


def test_names_round_trip_and_listing_orders_by_step_ignoring_other_files(tmp_path):
    assert checkpoint_name(7) == "step-000000007.ckpt" and checkpoint_step(Path("x") / checkpoint_name(123456)) == 123456
    with pytest.raises(ValueError, match=r"step-7.ckpt is not a checkpoint file name \(step-NNNNNNNNN.ckpt\)"):
        checkpoint_step(Path("step-7.ckpt"))
    for step in (100, 2, 10):
        save_checkpoint(tmp_path, step, payload(step))
    for other in ("step-7.ckpt", "step-000000003.ckpt.bak", ".step-000000004.ckpt.x1y2.tmp", "notes.txt"):
        (tmp_path / other).write_text("not a checkpoint")
    assert [p.name for p in list_checkpoints(tmp_path)] == [checkpoint_name(s) for s in (2, 10, 100)]
    assert list_checkpoints(tmp_path / "missing") == []


# ------------------------------------------------------------------------------------------------ writing


def test_save_only_latest_keeps_the_new_checkpoint_alone_and_other_files(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    for step in (1, 2, 3):
        save_checkpoint(tmp_path, step, payload(step, float(step)), only_latest=True)
    assert names(tmp_path) == ["notes.txt", checkpoint_name(3)]
    assert load_checkpoint(tmp_path / checkpoint_name(3))["model"]["means"][0, 0] == 3.0
    kept = tmp_path / "all"
    for step in (1, 2, 3):
        save_checkpoint(kept, step, payload(step))
    assert names(kept) == [checkpoint_name(s) for s in (1, 2, 3)]


def test_save_only_latest_removes_the_old_checkpoint_only_once_the_new_one_is_whole(tmp_path, monkeypatch):
    """While the new checkpoint is written the old one is still there; a crash mid-write (here after half the bytes)
    keeps the old one loadable and leaves no temp file."""
    save_checkpoint(tmp_path, 2, payload(2, 2.0), only_latest=True)
    real_save = torch.save
    seen_while_writing = []

    def write_and_look(obj, f, *args, **kwargs):
        seen_while_writing.append(names(tmp_path))
        real_save(obj, f, *args, **kwargs)

    monkeypatch.setattr(torch, "save", write_and_look)
    save_checkpoint(tmp_path, 4, payload(4, 4.0), only_latest=True)
    assert checkpoint_name(2) in seen_while_writing[0] and names(tmp_path) == [checkpoint_name(4)]

    def crash_half_way(obj, f, *args, **kwargs):
        real_save(obj, f, *args, **kwargs)
        Path(f).write_bytes(Path(f).read_bytes()[:100])
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", crash_half_way)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path, 6, payload(6, 6.0), only_latest=True)
    monkeypatch.undo()
    assert names(tmp_path) == [checkpoint_name(4)]
    assert load_checkpoint(tmp_path / checkpoint_name(4))["model"]["means"][0, 0] == 4.0


def test_a_hard_kill_mid_write_leaves_a_temp_file_that_nothing_mistakes_for_a_checkpoint(tmp_path, monkeypatch):
    """A kill -9 cannot run the clean-up: the temp file the real write used stays. It matches TEMP_PATTERN, no lookup
    takes it for a checkpoint, and remove_orphan_temp_files removes it and nothing else."""
    save_checkpoint(tmp_path, 2, payload(2))
    real_save = torch.save
    left_behind = []

    def killed(obj, f, *args, **kwargs):
        real_save(obj, f, *args, **kwargs)
        os.link(f, tmp_path / "kept-bytes")  # the bytes of the interrupted write, under the temp name below
        left_behind.append(Path(f).name)
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", killed)
    with pytest.raises(KeyboardInterrupt):
        save_checkpoint(tmp_path, 4, payload(4))
    monkeypatch.undo()
    orphan = tmp_path / left_behind[0]
    (tmp_path / "kept-bytes").rename(orphan)
    (tmp_path / ".config.yml.abc.tmp").write_text("another writer's temp file")
    assert TEMP_PATTERN.match(orphan.name) and orphan.name.startswith(".step-000000004.ckpt.")
    assert list_checkpoints(tmp_path) == [tmp_path / checkpoint_name(2)]
    assert find_checkpoint(tmp_path) == tmp_path / checkpoint_name(2)
    assert remove_orphan_temp_files(tmp_path) == [orphan]
    assert names(tmp_path) == [".config.yml.abc.tmp", checkpoint_name(2)]
    assert remove_orphan_temp_files(tmp_path / "missing") == []


def test_a_checkpoint_gets_the_mode_a_plain_write_gives(tmp_path):
    """The temp file behind the atomic write is created 0600; the checkpoint must not keep that (a shared run folder
    stays readable): a new one gets what open() gives, a rewritten one keeps its mode."""
    path = save_checkpoint(tmp_path, 1, payload(1))
    with open(tmp_path / "plain", "wb") as handle:
        handle.write(b"x")
    assert stat.S_IMODE(path.stat().st_mode) == stat.S_IMODE((tmp_path / "plain").stat().st_mode)
    path.chmod(0o640)
    save_checkpoint(tmp_path, 1, payload(1))
    assert stat.S_IMODE(path.stat().st_mode) == 0o640


@pytest.mark.parametrize("error", [PermissionError(errno.EACCES, "Permission denied"), RuntimeError("CUDA error")])
def test_a_write_error_that_is_not_a_full_disk_is_not_called_one(tmp_path, monkeypatch, error):
    def fail(obj, f, *args, **kwargs):
        raise error

    monkeypatch.setattr(torch, "save", fail)
    with pytest.raises(type(error)) as raised:
        save_checkpoint(tmp_path, 1, payload(1))
    assert not isinstance(raised.value, CheckpointError) and names(tmp_path) == []


# ------------------------------------------------------------------------------------------------ finding


def test_find_checkpoint_takes_the_newest_or_the_step_asked_for_from_a_run_folder(tmp_path):
    models = tmp_path / "run" / CHECKPOINT_DIR
    for step in (2, 10, 4):
        save_checkpoint(models, step, payload(step))
    for where in (tmp_path / "run", models):  # a run folder or its nerfstudio_models folder
        assert find_checkpoint(where) == models / checkpoint_name(10)
        assert find_checkpoint(where, 4) == models / checkpoint_name(4)
    with pytest.raises(CheckpointNotFoundError, match=rf"no checkpoint for step 3 in {models} \(has steps \[2, 4, 10\]\)"):
        find_checkpoint(tmp_path / "run", 3)


def test_find_checkpoint_names_an_empty_or_missing_folder(tmp_path):
    empty = tmp_path / "run" / CHECKPOINT_DIR
    empty.mkdir(parents=True)
    with pytest.raises(CheckpointNotFoundError, match=f"no checkpoint .* in {empty}: the run stopped before its first"):
        find_checkpoint(tmp_path / "run")
    with pytest.raises(CheckpointNotFoundError, match=f"checkpoint folder {tmp_path / 'nowhere'} does not exist"):
        find_checkpoint(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError):  # what callers outside the project catch
        find_checkpoint(tmp_path / "nowhere")
    with pytest.raises(CheckpointError, match=f"checkpoint {tmp_path / 'gone.ckpt'} does not exist"):
        load_checkpoint(tmp_path / "gone.ckpt")


# ------------------------------------------------------------------------------------------------ weights-only loading


def test_rng_states_come_back_and_continue_the_same_streams(tmp_path):
    """What a trainer stores of its random generators loads weights-only and, restored, draws what it would have."""
    torch.manual_seed(3)
    np.random.seed(3)
    random.seed(3)
    states = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    expected = (torch.rand(4), np.random.rand(4), [random.random() for _ in range(4)])
    path = save_checkpoint(tmp_path, 5, {**payload(5), "rng": states, "elapsed_s": 1.5, "note": None})
    loaded = load_checkpoint(path)
    torch.set_rng_state(loaded["rng"]["torch"])
    np.random.set_state(loaded["rng"]["numpy"])
    version, internal, gauss = loaded["rng"]["python"]
    random.setstate((version, tuple(internal), gauss))
    assert torch.equal(torch.rand(4), expected[0]) and np.array_equal(np.random.rand(4), expected[1])
    assert [random.random() for _ in range(4)] == expected[2]
    assert loaded["elapsed_s"] == 1.5 and loaded["note"] is None and loaded["step"] == 5


class _Call:
    """Pickles to ``function(*args)``: what unpickling would run with weights_only=False."""

    def __init__(self, function, *args):
        self.function, self.args = function, args

    def __reduce__(self):
        return self.function, self.args


@pytest.mark.parametrize("make", [
    lambda marker: _Call(os.system, f"touch {marker}"),
    lambda marker: _Call(subprocess.call, ["touch", str(marker)]),
    lambda marker: _Call(eval, f"__import__('pathlib').Path({str(marker)!r}).touch()"),
    lambda marker: _Call(shutil.copyfile, os.devnull, str(marker)),
], ids=["os.system", "subprocess.call", "eval", "shutil.copyfile"])
def test_a_checkpoint_that_would_run_code_is_refused_before_it_runs(tmp_path, make):
    marker = tmp_path / "code-ran"
    path = tmp_path / checkpoint_name(1)
    torch.save({**payload(1), "evil": make(marker)}, path)
    with pytest.raises(CheckpointError, match=f"checkpoint {path} holds objects other than tensors and plain values"):
        load_checkpoint(path)
    assert not marker.exists()


@pytest.mark.parametrize("value, global_name", [
    (OptimizersConfig(), "OptimizersConfig"),
    (Path("/tmp/x"), "PosixPath"),
    (np.float64(2.0), "scalar"),
    (np.zeros(3, np.float32), "Float32DType"),
], ids=["dataclass", "path", "numpy-scalar", "numpy-float32-array"])
def test_a_checkpoint_holding_objects_weights_only_refuses_is_named_as_such_not_as_truncated(tmp_path, value,
                                                                                             global_name):
    path = save_checkpoint(tmp_path, 1, {**payload(1), "extra": value})
    with pytest.raises(CheckpointError, match=rf"holds objects other than tensors and plain values \(\S*{global_name}\)"):
        load_checkpoint(path)


# ------------------------------------------------------------------------------------------------ does it fit


@pytest.fixture(scope="module")
def kc_config():
    config = copy.deepcopy(discover_methods()["kc-splatfacto"].config)
    config.pipeline.model.sh_degree = 3
    return config


def test_a_checkpoint_of_the_same_run_fits(kc_config, tmp_path):
    recorded = {"run": {"method_name": "kc-splatfacto", "sh_degree": 3}, "model": {"features_rest": torch.zeros(5, 15, 3)}}
    check_checkpoint_fits(recorded, kc_config, tmp_path / "a.ckpt")
    check_checkpoint_fits({"model": {"features_rest": torch.zeros(5, 15, 3)}}, kc_config, tmp_path / "a.ckpt")


@pytest.mark.parametrize("recorded, named", [
    ({"method_name": "splatfacto", "sh_degree": 3}, ["method_name 'splatfacto' in the checkpoint vs 'kc-splatfacto'"]),
    ({"method_name": "kc-splatfacto", "sh_degree": 1}, ["pipeline.model.sh_degree 1 in the checkpoint vs 3"]),
    ({"method_name": "splatfacto", "sh_degree": 2}, ["method_name 'splatfacto'", "pipeline.model.sh_degree 2"]),
])
def test_a_checkpoint_of_another_run_is_refused_naming_each_field_and_the_fix(kc_config, tmp_path, recorded, named):
    path = tmp_path / checkpoint_name(4)
    with pytest.raises(CheckpointError) as raised:
        check_checkpoint_fits({"run": recorded, "model": {}}, kc_config, path)
    message = str(raised.value)
    assert message.startswith(f"checkpoint {path} was written by another run (")
    assert all(part in message for part in named), message
    assert message.endswith("pass the config.yml of the run that wrote it")


def test_another_method_is_accepted_when_the_method_may_differ(kc_config, tmp_path):
    other = {"run": {"method_name": "splatfacto", "sh_degree": 3}, "model": {}}
    check_checkpoint_fits(other, kc_config, tmp_path / "a.ckpt", same_method=False)
    other["run"]["sh_degree"] = 0
    with pytest.raises(CheckpointError, match="pipeline.model.sh_degree 0 in the checkpoint vs 3") as raised:
        check_checkpoint_fits(other, kc_config, tmp_path / "a.ckpt", same_method=False)
    assert "method_name" not in str(raised.value)


@pytest.mark.parametrize("stored", [0, 1, 2, 3])
@pytest.mark.parametrize("configured", [0, 1, 2, 3])
def test_a_checkpoint_without_a_recorded_identity_is_checked_by_its_sh_coefficients(kc_config, tmp_path, stored,
                                                                                   configured):
    """Checkpoints of earlier versions record no identity: features_rest's width tells their SH degree."""
    config = copy.deepcopy(kc_config)
    config.pipeline.model.sh_degree = configured
    checkpoint = {"model": {"features_rest": torch.zeros(4, SH_REST[stored], 3)}}
    if stored == configured:
        check_checkpoint_fits(checkpoint, config, tmp_path / "old.ckpt")
        return
    with pytest.raises(CheckpointError, match=rf"features_rest holds {SH_REST[stored]} SH coefficients per colour, "
                                              rf"pipeline.model.sh_degree {configured} has {SH_REST[configured]}"):
        check_checkpoint_fits(checkpoint, config, tmp_path / "old.ckpt")
