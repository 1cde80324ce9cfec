"""kc_splatfacto/engine/loggers.py: tensorboard and offline wandb mirror metrics.jsonl (read back by the packages'
own readers and compared with the JSON log)."""

from __future__ import annotations

import json
import math
import struct
import sys
import time
import zlib

import pytest

from kc_splatfacto.engine.loggers import flatten_record
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.errors import UserError
from tests.training_utils import TINY_HEIGHT, TINY_WIDTH, tiny_demo_config

STEPS = 30


def test_flatten_record_names_every_finite_number():
    record = {"kind": "train", "step": 10, "loss": 0.5, "psnr": float("nan"), "kurtosis_render": [1.0, 2.0],
              "shares": {"kc_loss": {"share": 0.1}}, "split": "test", "flag": True, "train_s": 3.0}
    assert flatten_record(record) == {"train/loss": 0.5, "train/kurtosis_render/0": 1.0, "train/kurtosis_render/1": 2.0,
                                      "train/shares/kc_loss/share": 0.1, "train/train_s": 3.0}
    assert "eval/train_s" not in flatten_record({"kind": "eval", "step": 1, "train_s": 2.0, "psnr": 20.0})


@pytest.fixture(scope="module")
def tensorboard_run(tmp_path_factory):
    pytest.importorskip("tensorboard", reason="pip install 'kc-splatfacto[tensorboard]'")
    config = tiny_demo_config("kc-splatfacto", tmp_path_factory.mktemp("tb"), iterations=STEPS)
    config.logging.tensorboard = True
    config.eval_at_steps = (10,)
    return Trainer(config).train()


def test_tensorboard_event_files_hold_the_metrics_log(tensorboard_run):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(tensorboard_run), size_guidance={"scalars": 0, "images": 0})
    events.Reload()
    scalars = {tag: {e.step: e.value for e in events.Scalars(tag)} for tag in events.Tags()["scalars"]}
    records = read_metrics(tensorboard_run / "metrics.jsonl")
    train = [r for r in records if r["kind"] == "train"]
    evals = [r for r in records if r["kind"] == "eval"]
    assert len(train) == STEPS // 10 and [r["step"] for r in evals] == [10, STEPS]
    for record in train:
        for key in ("loss", "main_loss", "wavelet_loss", "kc_loss", "cbc_loss", "psnr", "gaussian_count"):
            assert math.isclose(scalars[f"train/{key}"][record["step"]], record[key], rel_tol=1e-6), key
    for previous, record in zip(train, train[1:]):
        expected = (record["train_s"] - previous["train_s"]) / (record["step"] - previous["step"])
        assert math.isclose(scalars["train/step_time_s"][record["step"]], expected, rel_tol=1e-5)
    for record in evals:
        for key in ("psnr", "ssim", "lpips"):
            if record.get(key) is not None:
                assert math.isclose(scalars[f"eval/{key}"][record["step"]], record[key], rel_tol=1e-6), key
    images = events.Images("eval/view_0")
    assert [image.step for image in images] == [10, STEPS]
    assert (images[-1].height, images[-1].width) == (TINY_HEIGHT, 2 * TINY_WIDTH)  # render beside ground truth


def _wandb_records(path):
    """The protobuf records of a .wandb file (a LevelDB log after a 7-byte W&B header), read independently of
    wandb's own writer. wandb's service process writes the file while it is read: the records end at the first
    chunk that is cut short or whose checksum (CRC-32 of its type byte and data, as W&B writes it) does not match
    yet, so a half-written tail is never parsed."""
    block = 32768
    data = path.read_bytes()
    assert data[:4] == b":W&B"
    pos, pending = 7, b""
    while pos + 7 <= len(data):
        if block - pos % block < 7:  # a block's tail too short for a header is padding
            pos += block - pos % block
            continue
        checksum, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        chunk = data[pos + 7:pos + 7 + length]
        if len(chunk) < length or zlib.crc32(bytes([kind]) + chunk) != checksum:
            return
        pos += 7 + length
        if kind == 1:
            yield chunk
        elif kind in (2, 3):
            pending = (pending if kind == 3 else b"") + chunk
        elif kind == 4:
            yield pending + chunk


def test_wandb_offline_run_holds_the_metrics_log(tmp_path):
    pytest.importorskip("wandb", reason="pip install 'kc-splatfacto[wandb]'")
    from wandb.proto import wandb_internal_pb2

    config = tiny_demo_config("splatfacto", tmp_path, iterations=20)
    config.logging.wandb = True
    run_dir = Trainer(config).train()
    files = list((run_dir / "wandb").glob("offline-run-*/run-*.wandb"))
    assert len(files) == 1

    def read() -> tuple[dict, bool]:
        history, finished = {}, False
        for raw in _wandb_records(files[0]):
            record = wandb_internal_pb2.Record()
            record.ParseFromString(raw)
            kind = record.WhichOneof("record_type")
            finished |= kind == "exit"
            if kind == "history":
                items = {(i.key or "/".join(i.nested_key)): json.loads(i.value_json) for i in record.history.item}
                history.setdefault(items["_step"], {}).update(items)
        return history, finished

    # wandb's service process may still be writing the file when finish() has returned: wait for its exit record
    deadline = time.monotonic() + 60
    history, finished = read()
    while not finished and time.monotonic() < deadline:
        time.sleep(0.5)
        history, finished = read()
    assert finished, "the offline run's log has no exit record"
    # a tail the service has not finished writing (cut short, or not yet filled in) ends the records read, never
    # a parse error: what such a read gives is a prefix of the whole log
    whole = list(_wandb_records(files[0]))
    data = files[0].read_bytes()
    cut, garbled = tmp_path / "cut.wandb", tmp_path / "garbled.wandb"
    cut.write_bytes(data[:len(data) - 5])
    garbled.write_bytes(data[:-1] + bytes([data[-1] ^ 0xFF]))
    for partial in (cut, garbled):
        records = list(_wandb_records(partial))
        assert records == whole[:len(records)] and len(records) < len(whole)
    train = [r for r in read_metrics(run_dir / "metrics.jsonl") if r["kind"] == "train"]
    assert train
    for record in train:
        assert math.isclose(history[record["step"]]["train/loss"], record["loss"], rel_tol=1e-9)
        assert history[record["step"]]["train/gaussian_count"] == record["gaussian_count"]
    assert "eval/psnr" in history[20] and history[20]["eval/view_0/_type"] == "image-file"


@pytest.mark.parametrize("flag, module", [("--logging.tensorboard", "torch.utils.tensorboard"),
                                          ("--logging.wandb", "wandb")])
def test_a_missing_backend_is_one_line_with_the_install_command(flag, module, monkeypatch, capsys, tmp_path):
    from kc_splatfacto.cli.train import entrypoint

    monkeypatch.setitem(sys.modules, module, None)
    code = entrypoint(["splatfacto", "--data", "demo", "--output-dir", str(tmp_path), flag])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert flag in err and "pip install 'kc-splatfacto[" in err
    assert not list(tmp_path.rglob("metrics.jsonl"))  # refused before training


def test_missing_backend_refused_before_setup(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)
    config = tiny_demo_config("splatfacto", tmp_path)
    config.logging.tensorboard = True
    with pytest.raises(UserError, match="tensorboard"):
        Trainer(config).setup()


# ------------------------------------------------------------------------- issue 37: a backend failing mid-run
class _FailingSink:
    """A logging backend that raises on the record of step ``at`` (a wandb writer losing its folder, say)."""

    def __init__(self, at: int):
        self.at = at

    def write(self, record):
        if record["kind"] == "train" and record["step"] >= self.at:
            raise RuntimeError("backend lost its connection")

    def close(self):
        pass


def _final_state(run_dir):
    from kc_splatfacto.engine.checkpoints import list_checkpoints, load_checkpoint

    ckpt = load_checkpoint(list_checkpoints(run_dir / "nerfstudio_models")[-1])
    assert ckpt["step"] == 30
    return dict(ckpt["model"])


def test_a_backend_failing_mid_run_stops_with_a_checkpoint_and_the_resume_loses_nothing(tmp_path):
    """A failure of logging, not of the training math: the state of the last whole step is saved, one line says
    so, and resuming from it ends where an uninterrupted run ends, bit for bit."""
    import torch

    from kc_splatfacto.engine.metrics_log import LoggingFailedError

    whole = tiny_demo_config("splatfacto", tmp_path / "whole", iterations=30)
    whole_dir = Trainer(whole).train()

    config = tiny_demo_config("splatfacto", tmp_path / "cut", iterations=30)
    trainer = Trainer(config)
    trainer.add_callbacks(sinks=[_FailingSink(at=20)])
    with pytest.raises(LoggingFailedError) as caught:
        trainer.train()
    message = str(caught.value)
    assert "_FailingSink failed (RuntimeError: backend lost its connection) at step 20" in message
    assert "\n" not in message and "--load-dir" in message
    assert isinstance(caught.value, UserError)  # the CLI prints it as one line
    cut_dir = trainer.run_dir
    assert (cut_dir / "nerfstudio_models" / "step-000000020.ckpt").is_file()

    resumed = tiny_demo_config("splatfacto", tmp_path / "cut", iterations=30)
    resumed.load_dir = cut_dir / "nerfstudio_models"
    Trainer(resumed).train()
    a, b = _final_state(whole_dir), _final_state(cut_dir)
    assert any(k.endswith("means") for k in a) and a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_metrics_jsonl_that_cannot_be_written_stops_the_run_with_one_line(tmp_path, monkeypatch, capsys):
    """The disk fills under metrics.jsonl (root ignores file modes, so the write itself is made to fail): kc-train
    exits 2 with one line, and the checkpoint of the step is there."""
    from kc_splatfacto.cli.train import entrypoint
    from kc_splatfacto.engine import metrics_log

    real_write = metrics_log.MetricsWriter.write

    def full_disk(self, record):
        if record.get("step", 0) >= 10 and record["kind"] == "train":
            def write(text):
                raise OSError(28, "No space left on device")
            self._file.write = write
        real_write(self, record)

    monkeypatch.setattr(metrics_log.MetricsWriter, "write", full_disk)
    code = entrypoint(["splatfacto", "--data", "demo", "--output-dir", str(tmp_path), "--max-num-iterations", "40",
                       "--logging.steps-per-log", "10", "--logging.progress-bar", "False"])
    err = capsys.readouterr().err.strip()
    errors = [line for line in err.splitlines() if not line.startswith("kc-train: warning: ")]  # the demo's note
    assert code == 2 and len(errors) == 1 and errors[0].startswith("kc-train: error: "), err
    assert "No space left on device" in errors[0] and "at step 10" in errors[0]
    assert len(list(tmp_path.rglob("step-000000010.ckpt"))) == 1
