"""Small training runs on the generated demo scene at tiny resolution, shared by the trainer and e2e tests."""

from __future__ import annotations

import copy
import subprocess
import sys
import time
from pathlib import Path

from kc_splatfacto.data.demo import DemoDataParserConfig
from kc_splatfacto.engine.trainer import TrainerConfig
from kc_splatfacto.registry import discover_methods

TINY_WIDTH, TINY_HEIGHT = 64, 48


def tiny_demo_config(method: str, output_dir: Path, iterations: int = 60, steps_scale: float = 0.02,
                     **model_overrides) -> TrainerConfig:
    """``method``'s config on the 64x48 demo scene, schedules compressed, no progress bar, no periodic eval, with
    the fixed settings (the scene plan off: a test of the plan passes ``plan="on"``)."""
    config: TrainerConfig = copy.deepcopy(discover_methods()[method].config)
    config.pipeline.datamanager.dataparser = DemoDataParserConfig(width=TINY_WIDTH, height=TINY_HEIGHT)
    config.output_dir = Path(output_dir)
    config.experiment_name = "tiny-demo"
    config.timestamp = "run"
    config.max_num_iterations = iterations
    config.steps_per_eval_all_images = 0
    config.steps_per_save = 10**9
    config.logging.progress_bar = False
    config.logging.steps_per_log = 10
    config.machine.device = "cpu"
    model = config.pipeline.model
    model.steps_scale = steps_scale
    model.num_downscales = 0
    model.max_num_gaussians = 20000
    model.plan = "off"
    for key, value in model_overrides.items():
        if not hasattr(model, key):
            raise AttributeError(f"model config has no field {key}")
        setattr(model, key, value)
    return config


def demo_pipeline(tmp_path: Path, method: str = "kc-splatfacto", seed: int = 0, **model_overrides):
    """``method``'s pipeline on the tiny demo scene (:func:`tiny_demo_config`), seeded, in training mode, the demo
    images cached beside ``tmp_path`` (shared by a test's sub-folders). Returns (pipeline, config)."""
    import torch

    config = tiny_demo_config(method, tmp_path, **model_overrides)
    config.pipeline.datamanager.dataparser.demo_cache_dir = Path(tmp_path).parent / "demo-cache"
    torch.manual_seed(seed)
    pipeline = config.pipeline.setup(seed=seed, dataparser=config.pipeline.datamanager.resolve_dataparser())
    pipeline.model.train()
    return pipeline, config


def stop_after(trainer, steps_taken: int) -> None:
    """Have ``trainer`` stop as Ctrl-C stops it (finish the step, save, return) once ``steps_taken`` steps are
    taken: its own ``request_stop`` from inside the loop."""
    take_step = trainer.train_iteration

    def stopping(step: int):
        result = take_step(step)
        if step + 1 == steps_taken:
            trainer.request_stop()
        return result

    trainer.train_iteration = stopping


def poison_loss_at(model, steps) -> None:
    """The model's loss is NaN at each step in ``steps`` (its render and gradients otherwise as usual)."""
    original = model.get_loss_dict

    def poisoned(outputs, batch):
        losses = original(outputs, batch)
        if model.step in steps:
            losses["main_loss"] = losses["main_loss"] * float("nan")
        return losses

    model.get_loss_dict = poisoned


def interrupt_cli_training(tmp_path: Path, signum: int, timestamp: str, env: dict) -> tuple[subprocess.CompletedProcess, Path]:
    """Start ``kc-train splatfacto --data demo`` (a budget it never reaches) in ``tmp_path``, send ``signum`` once
    it has logged a training record, and wait for it to exit. Returns (the finished process, the run folder)."""
    proc = subprocess.Popen(
        [str(Path(sys.executable).parent / "kc-train"), "splatfacto", "--data", "demo", "--max-num-iterations",
         "100000", "--output-dir", str(tmp_path), "--logging.progress-bar", "False", "--logging.steps-per-log", "2",
         "--timestamp", timestamp, "--steps-per-eval-all-images", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
    )
    metrics = tmp_path / "demo" / "splatfacto" / timestamp / "metrics.jsonl"
    deadline = time.time() + 240
    while time.time() < deadline and not (metrics.exists() and '"kind": "train"' in metrics.read_text()):
        time.sleep(0.5)
    proc.send_signal(signum)
    stdout, stderr = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr), metrics.parent
