"""Training runs that used to "succeed" wrongly (issue 11): bad budgets, unwritable outputs, resumes of another run or
past the budget, leftovers of a hard kill, unsafe checkpoints and configs, a full disk, SIGTERM."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import random
import signal
from pathlib import Path

import pytest
import torch

from kc_splatfacto.data.detect import AutoDataParserConfig
from kc_splatfacto.engine.checkpoints import list_checkpoints, load_checkpoint, save_checkpoint
from kc_splatfacto.engine.config import load_config
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.run_guard import trim_metrics
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.errors import CheckpointError, ConfigFileError, ResumeError, UserError
from tests.training_utils import interrupt_cli_training, tiny_demo_config


def snapshot(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` with the hash of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest() for p in sorted(folder.rglob("*"))
            if p.is_file()}


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    """A 4-step kc-splatfacto demo run with checkpoints at steps 2 and 4 (both kept)."""
    config = tiny_demo_config("kc-splatfacto", tmp_path_factory.mktemp("finished"), iterations=4)
    config.steps_per_save = 2
    config.save_only_latest_checkpoint = False
    config.logging.steps_per_log = 1
    return Trainer(config).train()


def resume_config(run_dir: Path, tmp_path: Path, method: str = "kc-splatfacto", iterations: int = 4, **fields):
    config = tiny_demo_config(method, tmp_path / "new-runs", iterations=iterations)
    config.load_dir = run_dir / "nerfstudio_models"
    for key, value in fields.items():
        setattr(config, key, value)
    return config


# ------------------------------------------------------------------------------------------------ settings


@pytest.mark.parametrize("iterations", [0, -5])
def test_non_positive_iterations_are_refused_when_the_trainer_is_built(tmp_path, iterations):
    config = tiny_demo_config("splatfacto", tmp_path, iterations=iterations)
    with pytest.raises(UserError, match=f"max_num_iterations = {iterations} is not allowed: --max-num-iterations must "
                                        "be at least 1"):
        Trainer(config)  # validated once, before anything is resolved, loaded or written
    assert not (tmp_path / "tiny-demo").exists()  # no run folder without a checkpoint


def test_unwritable_output_folder_is_refused_before_the_data_loads(tmp_path):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    config = tiny_demo_config("splatfacto", blocker / "outputs", iterations=2)
    config.pipeline.datamanager.dataparser = AutoDataParserConfig(data=tmp_path / "no-such-scene")  # would fail first
    # if the data loaded first
    with pytest.raises(UserError, match=f"--output-dir {blocker / 'outputs'} is not a writable folder"):
        Trainer(config).train()


# ------------------------------------------------------------------------------------------------ resume


def test_resume_of_another_method_is_refused_and_leaves_that_run_untouched(finished_run, tmp_path):
    before = snapshot(finished_run)
    config = resume_config(finished_run, tmp_path, method="splatfacto")
    with pytest.raises(ResumeError, match="is another run \\(method kc-splatfacto vs splatfacto\\).*--resume-from"):
        Trainer(config).train()
    assert snapshot(finished_run) == before


def test_resume_of_another_scene_is_refused(finished_run, tmp_path):
    from kc_splatfacto.data.demo import DemoDataParserConfig

    config = resume_config(finished_run, tmp_path)
    other = tmp_path / "other-scene"
    other.mkdir()
    config.pipeline.datamanager.dataparser = DemoDataParserConfig(data=other, width=64, height=48)
    with pytest.raises(ResumeError, match=f"scene demo vs {other}"):
        Trainer(config).train()


def test_override_resumes_another_run_into_a_new_folder(finished_run, tmp_path):
    before = snapshot(finished_run)
    config = resume_config(finished_run, tmp_path, method="splatfacto", iterations=6, resume_from_other_run=True)
    trainer = Trainer(config)
    run_dir = trainer.train()
    assert run_dir != finished_run and run_dir.is_relative_to(tmp_path / "new-runs")
    assert trainer.start_step == 4
    assert [p.name for p in list_checkpoints(run_dir / "nerfstudio_models")] == ["step-000000006.ckpt"]
    assert snapshot(finished_run) == before  # read, never written


def test_resume_past_the_budget_is_an_error_and_rewrites_nothing(finished_run, tmp_path):
    before = snapshot(finished_run)
    config = resume_config(finished_run, tmp_path, iterations=3)
    with pytest.raises(ResumeError, match="at step 4, past --max-num-iterations 3"):
        Trainer(config).train()
    assert snapshot(finished_run) == before


def test_resume_removes_orphan_temp_files_and_keeps_metrics_monotonic(tmp_path):
    """A hard kill after the step-2 checkpoint: records of steps 3-4, a torn line and a checkpoint temp file remain.
    The resume drops the records after the checkpoint and the temp file; the log has no duplicate or backwards step."""
    config = tiny_demo_config("kc-splatfacto", tmp_path, iterations=4)
    config.steps_per_save, config.save_only_latest_checkpoint, config.logging.steps_per_log = 2, False, 1
    run_dir = Trainer(config).train()
    models = run_dir / "nerfstudio_models"
    (models / "step-000000004.ckpt").unlink()  # the kill came before the step-4 checkpoint
    orphan = models / ".step-000000004.ckpt.k9x2.tmp"
    orphan.write_bytes(b"half a checkpoint")
    with (run_dir / "metrics.jsonl").open("a") as log:
        log.write('{"kind": "train", "step": 4, "los')  # torn by the kill
    assert max(r["step"] for r in read_metrics_lines(run_dir)) == 4

    again = tiny_demo_config("kc-splatfacto", tmp_path, iterations=4)
    again.logging.steps_per_log = 1
    again.load_dir = models
    trainer = Trainer(again)
    assert trainer.train() == run_dir and trainer.start_step == 2
    assert not orphan.exists()
    records = read_metrics(run_dir / "metrics.jsonl")  # parses: the torn line is gone
    for kind in ("train", "checkpoint"):
        steps = [r["step"] for r in records if r["kind"] == kind]
        assert steps == sorted(set(steps)), (kind, steps)  # strictly increasing
    assert [r["step"] for r in records if r["kind"] == "train"] == [1, 2, 3, 4]


def read_metrics_lines(run_dir):
    out = []
    for line in (run_dir / "metrics.jsonl").read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            pass
    return out


def test_trim_metrics_keeps_records_up_to_the_step(tmp_path):
    path = tmp_path / "metrics.jsonl"
    records = [{"kind": "train", "step": s} for s in (1, 2, 3, 4)] + [{"kind": "note"}]
    path.write_text("".join(json.dumps(r) + "\n" for r in records) + '{"kind": "tr')
    assert trim_metrics(path, 2) == 3  # steps 3, 4 and the torn line
    assert read_metrics(path) == [records[0], records[1], records[4]]
    assert trim_metrics(path, 2) == 0


# ------------------------------------------------------------------------------------------------ checkpoints


class _Payload:
    """Pickles to a call of Path.touch: what a hostile checkpoint would run with weights_only=False."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


def test_checkpoint_that_would_run_code_is_refused(tmp_path):
    marker = tmp_path / "code-ran"
    path = tmp_path / "step-000000001.ckpt"
    torch.save({"step": 1, "model": {}, "evil": _Payload(marker)}, path)
    with pytest.raises(CheckpointError, match=f"checkpoint {path} holds objects other than tensors"):
        load_checkpoint(path)
    assert not marker.exists()


def test_truncated_and_garbage_checkpoints_are_named(finished_run, tmp_path):
    good = finished_run / "nerfstudio_models" / "step-000000004.ckpt"
    assert load_checkpoint(good)["step"] == 4  # a real checkpoint (numpy RNG state included) loads weights-only
    cut = tmp_path / "step-000000004.ckpt"
    data = good.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=f"checkpoint {cut} is truncated or not a checkpoint"):
        load_checkpoint(cut)
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(os.urandom(4096))
    with pytest.raises(CheckpointError, match=f"checkpoint {garbage} is truncated or not a checkpoint"):
        load_checkpoint(garbage)
    # bytes that make the unpickler fail with IndexError, KeyError and struct.error (not unpickling errors)
    for name, data in (("index", random.Random(2).randbytes(4096)), ("key", random.Random(20).randbytes(4096)),
                       ("struct", b"\x80\x02}q\x00(X")):
        odd = tmp_path / f"{name}.ckpt"
        odd.write_bytes(data)
        with pytest.raises(CheckpointError, match=f"checkpoint {odd} is truncated or not a checkpoint"):
            load_checkpoint(odd)
    not_ours = tmp_path / "other.ckpt"
    torch.save({"weights": torch.ones(2)}, not_ours)
    with pytest.raises(CheckpointError, match="not a kc-splatfacto checkpoint"):
        load_checkpoint(not_ours)


def test_full_disk_during_a_checkpoint_write_is_named_and_keeps_the_previous_one(tmp_path, monkeypatch):
    first = save_checkpoint(tmp_path, 2, {"step": 2, "model": {"w": torch.ones(3)}})

    def full_disk(obj, f, *args, **kwargs):
        Path(f).write_bytes(b"partial")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full_disk)
    target = tmp_path / "step-000000004.ckpt"
    with pytest.raises(CheckpointError, match=f"could not write checkpoint {target} .*disk full"):
        save_checkpoint(tmp_path, 4, {"step": 4, "model": {}})
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == [first.name]
    assert load_checkpoint(first)["model"]["w"].tolist() == [1.0, 1.0, 1.0]


# ------------------------------------------------------------------------------------------------ config.yml


@pytest.mark.parametrize(
    "payload",
    [
        "!!python/object/apply:pathlib.Path.touch [!!python/object/apply:pathlib.PosixPath ['{marker}']]",
        "!!python/object/apply:os.system ['touch {marker}']",
        "!!python/object/new:subprocess.Popen [['touch', '{marker}']]",
        "!!python/object:subprocess.Popen {{}}",
        "!!python/name:os.system",
    ],
)
def test_config_that_would_run_code_is_refused(finished_run, tmp_path, payload):
    marker = tmp_path / "code-ran"
    text = (finished_run / "config.yml").read_text()
    assert "\nmethod_name: kc-splatfacto\n" in text
    evil = tmp_path / "config.yml"
    evil.write_text(text.replace("\nmethod_name: kc-splatfacto\n", "\nmethod_name: " + payload.format(marker=marker)
                                 + "\n"))
    assert yaml_line_of(evil, "method_name:") is not None
    with pytest.raises(ConfigFileError, match=f"{evil}:{yaml_line_of(evil, 'method_name:')}: .*"):
        load_config(evil)
    assert not marker.exists()


def yaml_line_of(path, prefix):
    return next((i for i, line in enumerate(path.read_text().splitlines(), 1) if line.startswith(prefix)), None)


def test_garbage_config_is_named(tmp_path):
    garbage = tmp_path / "config.yml"
    garbage.write_bytes(b"\x00\x01: [unclosed\n  - {")
    with pytest.raises(ConfigFileError, match=f"{garbage} is not valid YAML"):
        load_config(garbage)


def test_real_config_round_trips_through_the_safe_loader(finished_run):
    import yaml

    text = (finished_run / "config.yml").read_text()
    assert load_config(finished_run / "config.yml") == yaml.unsafe_load(text)


# ------------------------------------------------------------------------------------------------ the scene path

REPO = Path(__file__).resolve().parents[2]
COMMITTED_CONFIGS = sorted((REPO / "docs" / "results").rglob("config.yml"))
#: where the classes were when earlier versions wrote config.yml (PyYAML names the class's module)
EARLIER_CLASS_NAMES = {
    "kc_splatfacto.engine.trainer.TrainerConfig": "kc_splatfacto.engine.config.TrainerConfig",
    "kc_splatfacto.engine.pipeline.PipelineConfig": "kc_splatfacto.engine.config.PipelineConfig",
    "kc_splatfacto.engine.datamanager.DataManagerConfig": "kc_splatfacto.engine.config.DataManagerConfig",
    "kc_splatfacto.engine.base_config.MachineConfig": "kc_splatfacto.engine.config.MachineConfig",
    "kc_splatfacto.engine.base_config.LoggingConfig": "kc_splatfacto.engine.config.LoggingConfig",
}


@pytest.mark.parametrize("path", COMMITTED_CONFIGS, ids=lambda p: str(p.relative_to(REPO / "docs" / "results")))
def test_committed_config_files_load_with_their_scene(path):
    """config.yml files earlier code wrote (the scene in three fields, classes named where they were) still load, and
    the scene they name is the one their recorded dataparser holds (PyYAML's unsafe loader: the oracle)."""
    import yaml

    from kc_splatfacto.engine.run_guard import comparable_dataparser, scene_of

    config = load_config(path)
    raw = yaml.unsafe_load(path.read_text())  # the file's objects as written (fields added since are absent)
    assert (config.method_name, config.max_num_iterations) == (raw.method_name, raw.max_num_iterations)
    assert scene_of(comparable_dataparser(config)) == str(Path(raw.pipeline.datamanager.dataparser.data).resolve())


@pytest.mark.parametrize("path", COMMITTED_CONFIGS, ids=lambda p: str(p.relative_to(REPO / "docs" / "results")))
def test_committed_runs_are_finished(path):
    """A committed study run is a whole run: its metrics.jsonl holds the test evaluation at the step its config.yml
    ends at. A run cut off by a session's end restarts from scratch (checkpoints are not committed), so its partial
    log must not be committed: a report or a reader of the folder would take it for a run."""
    import json
    import re

    end = re.search(r"^max_num_iterations: (\d+)$", path.read_text(), re.MULTILINE)
    assert end, f"{path}: no max_num_iterations line"
    metrics = path.parent / "metrics.jsonl"
    assert metrics.is_file(), f"{path.parent}: config.yml without metrics.jsonl"
    records = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    final_test_eval = (r.get("kind") == "eval" and r.get("step") == int(end[1]) and r.get("split", "test") == "test"
                       for r in records)
    assert any(final_test_eval), (
        f"{metrics}: no test evaluation at step {end[1]}: an unfinished run; remove it from the commit "
        "(kc-bench --resume runs it again)"
    )


def test_config_file_naming_classes_where_earlier_versions_had_them_loads(finished_run, tmp_path):
    text = (finished_run / "config.yml").read_text()
    for now, before in EARLIER_CLASS_NAMES.items():
        assert f"!!python/object:{now}" in text
        text = text.replace(f"!!python/object:{now}", f"!!python/object:{before}")
    old = tmp_path / "config.yml"
    old.write_text(text)
    assert load_config(old) == load_config(finished_run / "config.yml")


def test_a_run_records_its_scene_once_and_resolves_it_once(tmp_path, monkeypatch):
    """The dataparser is resolved once, when the run is planned; the data manager loads that object, and config.yml
    holds the scene in the recorded dataparser alone."""
    from kc_splatfacto.engine.datamanager import DataManagerConfig

    calls = []
    resolve = DataManagerConfig.resolve_dataparser
    monkeypatch.setattr(DataManagerConfig, "resolve_dataparser", lambda self: calls.append(1) or resolve(self))
    config = tiny_demo_config("splatfacto", tmp_path, iterations=1)
    config.pipeline.datamanager.set_scene("demo")
    trainer = Trainer(config)
    run_dir = trainer.train()
    assert len(calls) == 1
    assert trainer.datamanager.dataparser_config is trainer.dataparser
    recorded = load_config(run_dir / "config.yml")
    assert str(recorded.pipeline.datamanager.dataparser.data) == "demo"


def _with_old_scene_fields(config_yml: Path, trainer_data: str, datamanager_data: str) -> str:
    """The config.yml text as earlier versions wrote it: a ``data`` field in the trainer's and the data manager's
    mappings (the --data alias and the data manager's copy of the scene)."""
    lines = config_yml.read_text().splitlines()
    out = []
    for line in lines:
        out.append(line)
        if line.startswith("!!python/object:kc_splatfacto.engine.trainer.TrainerConfig"):
            out.append(f"data: {trainer_data}")
        if line.strip().startswith("datamanager: !!python/object:"):
            out.append(f"    data: {datamanager_data}")
    assert len(out) == len(lines) + 2, "the dump's layout changed: this test's edit found no place"
    return "\n".join(out) + "\n"


def test_a_run_recorded_with_the_scene_in_the_fields_of_earlier_versions_is_the_same_run(finished_run, tmp_path):
    """Earlier versions held the scene in three fields (the trainer's --data alias, the data manager's, the
    dataparser's); their config.yml files read back with the scene in the dataparser's alone, the same run."""
    from kc_splatfacto.engine.run_guard import differences, setting_differences

    stored = load_config(finished_run / "config.yml")
    (tmp_path / "config.yml").write_text(_with_old_scene_fields(finished_run / "config.yml", "null", "null"))
    old_style = load_config(tmp_path / "config.yml")
    assert differences(old_style, stored, parser_settings=True) == []
    assert setting_differences(old_style, stored) == []
    (tmp_path / "config.yml").write_text(_with_old_scene_fields(finished_run / "config.yml", "null", str(tmp_path)))
    moved = load_config(tmp_path / "config.yml")  # a scene in the data manager's field: the dataparser's now
    assert moved.pipeline.datamanager.dataparser.data == tmp_path
    assert differences(stored, moved) == [f"scene demo vs {tmp_path.resolve()}"]


# ------------------------------------------------------------------------------------------------ SIGTERM


def test_sigterm_saves_a_checkpoint_and_exits_cleanly(tmp_path):
    env = dict(os.environ, KC_SPLATFACTO_CACHE=str(tmp_path / "cache"))
    proc, run_dir = interrupt_cli_training(tmp_path, signal.SIGTERM, "term", env)
    stdout, stderr = proc.stdout, proc.stderr
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    assert "interrupted at step" in stdout
    checkpoints = list_checkpoints(run_dir / "nerfstudio_models")
    assert len(checkpoints) == 1 and int(checkpoints[0].stem.split("-")[1]) >= 2



# ------------------------------------------------------------------------------------------------ issue 26


def test_resume_with_other_settings_names_them_and_override_continues_in_a_new_folder(tmp_path):
    config = tiny_demo_config("splatfacto", tmp_path, iterations=2)
    run_dir = Trainer(config).train()
    before = snapshot(run_dir)
    again = tiny_demo_config("splatfacto", tmp_path, iterations=3)
    again.load_dir = run_dir
    again.pipeline.model.cull_alpha_thresh = 0.2
    again.optimizers.means.optimizer.lr = 1e-4
    with pytest.raises(ResumeError) as info:
        Trainer(again).train()
    message = str(info.value)
    assert "pipeline.model.cull_alpha_thresh 0.1 vs 0.2" in message
    assert "optimizers.means.optimizer.lr 0.00016 vs 0.0001" in message
    assert snapshot(run_dir) == before
    again.resume_from_other_run = True
    again.timestamp = "other"
    trainer = Trainer(again)
    new_dir = trainer.train()
    assert new_dir != run_dir and trainer.start_step == 2
    assert snapshot(run_dir) == before


def test_load_dir_may_name_the_checkpoint_file(tmp_path):
    from kc_splatfacto.engine.checkpoints import CheckpointNotFoundError, find_checkpoint

    config = tiny_demo_config("splatfacto", tmp_path, iterations=2)
    config.steps_per_save, config.save_only_latest_checkpoint = 1, False
    run_dir = Trainer(config).train()
    first = run_dir / "nerfstudio_models" / "step-000000001.ckpt"
    assert find_checkpoint(first) == first and find_checkpoint(first, 1) == first
    with pytest.raises(CheckpointNotFoundError, match="is the checkpoint of step 1, not of the step 2"):
        find_checkpoint(first, 2)
    (run_dir / "notes.txt").write_text("x")
    with pytest.raises(CheckpointNotFoundError, match="not a step-XXXXXXXXX.ckpt"):
        find_checkpoint(run_dir / "notes.txt")


def test_missing_fields_are_the_lines_a_config_lost(tmp_path):
    """Issue 37, category 6: the reader fills a lost line with the field's default, so only the file tells; the
    dotted names of exactly the removed lines come back (a nested one with its path), none for the file as written."""
    from kc_splatfacto.engine.config_file import missing_fields, save_config
    from kc_splatfacto.engine.trainer import TrainerConfig

    path = tmp_path / "config.yml"
    save_config(tiny_demo_config("kc-splatfacto", tmp_path / "out"), path)
    assert missing_fields(path, load_config(path)) == []
    lines = path.read_text().splitlines(keepends=True)
    lost = ("method_name:", "      kc_weight:", "      width:")
    path.write_text("".join(line for line in lines if not line.startswith(lost)))
    assert sorted(missing_fields(path, load_config(path))) == [
        "method_name", "pipeline.datamanager.dataparser.width", "pipeline.model.frequency.kc_weight"]
    assert load_config(path).method_name == TrainerConfig().method_name  # the default, without a word
