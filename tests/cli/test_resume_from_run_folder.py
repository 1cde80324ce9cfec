"""``kc-train --load-dir RUN`` / ``--load-config RUN/config.yml`` with no method and no scene: the run's config.yml
gives the method, scene, dataparser and every setting; flags beside it override (one line each); a moved scene is
named with ``--data NEW_PATH`` (issue 68, part 3).

One tiny run (the 40x30 demo images copied into a scene folder, splatfacto with its schedules compressed so density
control runs after the stop) is stopped after step 3 of 6 as Ctrl-C stops it, once per module; each test resumes its own copy of it
through the real ``kc_splatfacto.cli.train.entrypoint``. The uninterrupted 6-step run is the reference: a resume is
bit-identical to it on the CPU.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from kc_splatfacto.cli import train as kc_train
from kc_splatfacto.data.demo import DemoSceneSpec, ensure_demo_scene
from kc_splatfacto.engine.checkpoints import CHECKPOINT_DIR, list_checkpoints, load_checkpoint
from kc_splatfacto.engine.config_file import read_config_file
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.trainer import Trainer, TrainerConfig
from tests.training_utils import stop_after

TINY = {"width": 40, "height": 30, "num_cameras": 4, "num_points": 50}
STEPS, STOP_AT = 6, 3


def train_args(scene: Path, output_dir: Path, timestamp: str = "run", steps: int = STEPS) -> list[str]:
    """A full kc-train command line of a tiny run on ``scene`` (the one the shared run was started with)."""
    return ["splatfacto", "--data", str(scene), "--output-dir", str(output_dir), "--timestamp", timestamp,
            "--max-num-iterations", str(steps), "--steps-per-eval-all-images", "0", "--final-lpips-nets",
            "--logging.progress-bar", "False", "--logging.steps-per-log", "1", "--machine.device", "cpu",
            "--pipeline.model.steps-scale", "0.004", "--pipeline.model.num-downscales", "0"]


def tiny_scene(folder: Path, cache: Path, **spec) -> Path:
    """A copy of a tiny generated demo scene (a SPARS3R folder) at ``folder``."""
    shutil.copytree(ensure_demo_scene(DemoSceneSpec(**{**TINY, **spec}), cache), folder)
    return folder


def gaussians(run_dir: Path, step: int = STEPS) -> dict[str, torch.Tensor]:
    return load_checkpoint(run_dir / CHECKPOINT_DIR / f"step-{step:09d}.ckpt")["model"]


def assert_same_gaussians(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert sorted(a) == sorted(b)
    for name in a:
        assert torch.equal(a[name], b[name]), name


def steps_of(run_dir: Path, kind: str = "train") -> list[int]:
    return [r["step"] for r in read_metrics(run_dir / "metrics.jsonl") if r["kind"] == kind]


def notes(out: str) -> list[str]:
    """kc-train's own lines on stdout (the override lines)."""
    return [line for line in out.splitlines() if line.startswith("kc-train:")]


@dataclass
class SharedRun:
    root: Path
    scene: Path
    stopped: Path  # the run stopped after STOP_AT steps (never resumed in place: tests copy it)
    reference: dict[str, torch.Tensor]  # the uninterrupted run's Gaussians at STEPS

    def copy(self, where: Path) -> Path:
        return Path(shutil.copytree(self.stopped, where / "run"))


@pytest.fixture(scope="module")
def shared(tmp_path_factory) -> SharedRun:
    root = tmp_path_factory.mktemp("resume-from-run-folder")
    scene = tiny_scene(root / "scene", root / "cache")
    assert kc_train.entrypoint(train_args(scene, root / "outputs", timestamp="full")) == 0
    reference = gaussians(root / "outputs" / "scene" / "splatfacto" / "full")
    # the same command line, stopped after step STOP_AT as Ctrl-C stops it (finish the step, save, return)
    trainer = Trainer(kc_train.parse_command_line(train_args(scene, root / "outputs")))
    stop_after(trainer, STOP_AT)
    stopped = trainer.train()
    assert trainer.interrupted and [p.name for p in list_checkpoints(stopped / CHECKPOINT_DIR)] == [
        f"step-{STOP_AT:09d}.ckpt"]
    assert steps_of(stopped) == list(range(1, STOP_AT + 1))
    assert reference["means"].shape[0] != TINY["num_points"]  # density control runs in the steps a resume takes
    return SharedRun(root, scene, stopped, reference)


@pytest.mark.parametrize("spelling", ["run folder", "nerfstudio_models", "checkpoint file", "--load-config",
                                      "--load-step"])
def test_load_dir_alone_continues_the_same_run_bit_for_bit(shared, tmp_path, capsys, spelling):
    run = shared.copy(tmp_path)
    outputs_before = sorted(p.relative_to(shared.root) for p in (shared.root / "outputs").rglob("*"))
    argv = {"run folder": ["--load-dir", str(run)],
            "nerfstudio_models": ["--load-dir", str(run / CHECKPOINT_DIR)],
            "checkpoint file": ["--load-dir", str(run / CHECKPOINT_DIR / f"step-{STOP_AT:09d}.ckpt")],
            "--load-config": ["--load-config", str(run / "config.yml")],
            "--load-step": ["--load-dir", str(run), "--load-step", str(STOP_AT)]}[spelling]
    assert kc_train.entrypoint(argv) == 0
    out = capsys.readouterr().out
    assert notes(out) == []  # nothing overridden
    assert f"output folder: {run}" in out
    assert [p.name for p in list_checkpoints(run / CHECKPOINT_DIR)] == [f"step-{STEPS:09d}.ckpt"]
    assert steps_of(run) == list(range(1, STEPS + 1))  # one log, past the checkpoint's step, no step twice
    assert steps_of(run, "eval") == [STEPS]
    assert_same_gaussians(gaussians(run), shared.reference)  # as if never stopped
    # into the same run folder: nothing new beside the runs the fixture wrote
    assert sorted(p.relative_to(shared.root) for p in (shared.root / "outputs").rglob("*")) == outputs_before


def test_the_short_form_trains_what_the_full_command_line_does(shared, tmp_path, capsys):
    short, full = shared.copy(tmp_path / "short"), shared.copy(tmp_path / "full")
    assert kc_train.entrypoint(["--load-dir", str(short)]) == 0
    assert kc_train.entrypoint([*train_args(shared.scene, shared.root / "outputs"), "--load-dir", str(full)]) == 0
    assert_same_gaussians(gaussians(short), gaussians(full))
    assert_same_gaussians(gaussians(short), shared.reference)
    assert steps_of(short) == steps_of(full)
    recorded = read_config_file(short / "config.yml", TrainerConfig)
    assert recorded.pipeline.datamanager.dataparser == read_config_file(
        full / "config.yml", TrainerConfig).pipeline.datamanager.dataparser
    assert recorded.load_dir == short and recorded.timestamp == "run"  # the run's own settings, kept
    capsys.readouterr()


def test_a_flag_beside_it_overrides_the_recorded_value_and_says_so(shared, tmp_path, capsys):
    run = shared.copy(tmp_path)
    assert kc_train.entrypoint(["--load-dir", str(run), "--max-num-iterations", "8",
                                "--logging.steps-per-log", "2"]) == 0
    assert notes(capsys.readouterr().out) == ["kc-train: max_num_iterations 8 (the run recorded 6)",
                                              "kc-train: logging.steps_per_log 2 (the run recorded 1)"]
    assert [p.name for p in list_checkpoints(run / CHECKPOINT_DIR)] == ["step-000000008.ckpt"]
    assert steps_of(run) == [1, 2, 3, 4, 6, 8]
    recorded = read_config_file(run / "config.yml", TrainerConfig)
    assert (recorded.max_num_iterations, recorded.logging.steps_per_log) == (8, 2)


def test_an_override_the_run_guard_refuses_is_named_and_continues_elsewhere_on_request(shared, tmp_path, capsys):
    run = shared.copy(tmp_path)
    before = (run / "config.yml").read_text(), (run / "metrics.jsonl").read_text()
    assert kc_train.entrypoint(["--load-dir", str(run), "--pipeline.model.ssim-lambda", "0.5"]) == 2
    captured = capsys.readouterr()
    assert notes(captured.out) == ["kc-train: pipeline.model.ssim_lambda 0.5 (the run recorded 0.2)"]
    [error] = captured.err.strip().splitlines()
    assert error.startswith("kc-train: error: ") and "pipeline.model.ssim_lambda 0.2 vs 0.5" in error
    assert "--resume-from-other-run True" in error
    assert ((run / "config.yml").read_text(), (run / "metrics.jsonl").read_text()) == before

    elsewhere = tmp_path / "elsewhere"
    assert kc_train.entrypoint(["--load-dir", str(run), "--pipeline.model.ssim-lambda", "0.5",
                                "--resume-from-other-run", "True", "--output-dir", str(elsewhere)]) == 0
    out = capsys.readouterr().out
    assert notes(out) == [f"kc-train: output_dir {elsewhere} (the run recorded {shared.root / 'outputs'})",
                          "kc-train: pipeline.model.ssim_lambda 0.5 (the run recorded 0.2)"]
    new_run = elsewhere / "scene" / "splatfacto" / "run"
    assert f"output folder: {new_run}" in out
    assert (new_run / CHECKPOINT_DIR / f"step-{STEPS:09d}.ckpt").is_file()
    assert read_config_file(new_run / "config.yml", TrainerConfig).pipeline.model.ssim_lambda == 0.5
    assert ((run / "config.yml").read_text(), (run / "metrics.jsonl").read_text()) == before  # left untouched


def test_a_moved_scene_is_named_with_the_flag_to_pass_and_data_then_resumes(shared, tmp_path, capsys):
    scene = tiny_scene(tmp_path / "scene", shared.root / "cache")
    assert kc_train.entrypoint(train_args(scene, tmp_path / "outputs", steps=STOP_AT)) == 0
    run = tmp_path / "outputs" / "scene" / "splatfacto" / "run"
    moved = scene.rename(tmp_path / "moved-scene")
    capsys.readouterr()

    assert kc_train.entrypoint(["--load-dir", str(run), "--max-num-iterations", str(STEPS)]) == 2
    [error] = capsys.readouterr().err.strip().splitlines()
    assert error.startswith(f"kc-train: error: the scene {scene} that {run / 'config.yml'} records does not exist")
    assert "--data NEW_PATH" in error

    # another scene in its place (other cameras) is refused before anything is written
    other = tiny_scene(tmp_path / "other-scene", shared.root / "cache", num_cameras=6)
    files = ("config.yml", "metrics.jsonl", "dataparser_transforms.json")
    before = [(run / name).read_text() for name in files]
    assert kc_train.entrypoint(["--load-dir", str(run), "--data", str(other), "--max-num-iterations",
                                str(STEPS)]) == 2
    [error] = capsys.readouterr().err.strip().splitlines()
    assert f"--data {other} is not the scene of the run" in error and "dataparser_transforms.json" in error
    assert [p.name for p in list_checkpoints(run / CHECKPOINT_DIR)] == [f"step-{STOP_AT:09d}.ckpt"]
    assert [(run / name).read_text() for name in files] == before

    assert kc_train.entrypoint(["--load-dir", str(run), "--data", str(moved), "--max-num-iterations",
                                str(STEPS)]) == 0
    out = capsys.readouterr().out
    assert notes(out) == [f"kc-train: max_num_iterations {STEPS} (the run recorded {STOP_AT})",
                          f"kc-train: data {moved} (the run recorded {scene})"]  # in the config's field order
    assert f"output folder: {run}" in out
    assert [p.name for p in list_checkpoints(run / CHECKPOINT_DIR)] == [f"step-{STEPS:09d}.ckpt"]
    assert read_config_file(run / "config.yml", TrainerConfig).pipeline.datamanager.dataparser.data == moved
    assert kc_train.entrypoint(["--load-dir", str(run), "--max-num-iterations", "7"]) == 0  # found there now


def test_a_folder_without_config_yml_is_one_line_naming_the_file(shared, tmp_path, capsys):
    bare = tmp_path / "bare"
    shutil.copytree(shared.stopped / CHECKPOINT_DIR, bare / CHECKPOINT_DIR)
    for argv in (["--load-dir", str(bare)], ["--load-dir", str(bare / CHECKPOINT_DIR)], ["--load-config", str(bare)]):
        assert kc_train.entrypoint(argv) == 2
        [error] = capsys.readouterr().err.strip().splitlines()
        assert error.startswith("kc-train: error: ") and f"{bare / 'config.yml'} does not exist" in error, argv
    assert kc_train.entrypoint(["--load-dir", str(tmp_path / "nowhere")]) == 2
    [error] = capsys.readouterr().err.strip().splitlines()
    assert error.startswith(f"kc-train: error: --load-dir {tmp_path / 'nowhere'} does not exist")
    assert not (bare / "config.yml").exists()


def test_the_demo_scene_resumes_and_regenerates_into_its_cache(tmp_path, capsys):
    cache = tmp_path / "cache"
    args = train_args(Path("demo"), tmp_path / "outputs", steps=STOP_AT)
    assert kc_train.entrypoint([*args, "demo", *(f"--{k.replace('_', '-')}={v}" for k, v in TINY.items()),
                                "--demo-cache-dir", str(cache)]) == 0
    run = tmp_path / "outputs" / "demo" / "splatfacto" / "run"
    shutil.rmtree(cache)
    capsys.readouterr()
    assert kc_train.entrypoint(["--load-config", str(run / "config.yml"), "--max-num-iterations", "5"]) == 0
    assert notes(capsys.readouterr().out) == ["kc-train: max_num_iterations 5 (the run recorded 3)"]
    assert [p.name for p in list_checkpoints(run / CHECKPOINT_DIR)] == ["step-000000005.ckpt"]
    assert any(cache.glob("demo-*/demo.json"))  # generated again where the run said
    assert steps_of(run) == [1, 2, 3, 4, 5]


def test_kc_train_help_shows_the_short_form(capsys):
    with pytest.raises(SystemExit):
        kc_train.entrypoint(["--help"])
    assert "kc-train --load-dir RUN [FLAG VALUE ...]" in " ".join(capsys.readouterr().out.split())


def test_help_beside_load_dir_shows_the_runs_values(shared, capsys):
    with pytest.raises(SystemExit) as exit_info:
        kc_train.entrypoint(["--load-dir", str(shared.stopped), "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: kc-train --load-dir RUN [OPTIONS]")
    assert "--max-num-iterations INT" in out and f"(the run: {STEPS})" in out


def test_the_full_command_line_without_a_scene_points_to_the_short_form(shared, capsys):
    assert kc_train.entrypoint(["splatfacto", "--load-dir", str(shared.stopped)]) == 2
    [error] = capsys.readouterr().err.strip().splitlines()
    assert "no scene given: pass --data PATH" in error and "kc-train --load-dir RUN" in error
