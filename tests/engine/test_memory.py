"""A run's memory budget (issue 58 item 4): the start check of the Gaussian cap against the budget, and growth stopped
at the budget during training (one line, a record, a checkpoint at the end) instead of the kernel's kill."""

from __future__ import annotations

import json

import pytest
import torch

from kc_splatfacto.cli import train as kc_train
from kc_splatfacto.engine import memory
from kc_splatfacto.engine.checkpoints import list_checkpoints, load_checkpoint
from kc_splatfacto.engine.memory import MemoryGuard, bytes_per_gaussian, current_rss_bytes, peak_rss_since_reset

CPU = torch.device("cpu")


def test_bytes_per_gaussian_grows_with_the_image_and_is_positive():
    assert 0 < bytes_per_gaussian(64 * 48) <= bytes_per_gaussian(320 * 240) <= bytes_per_gaussian(1920 * 1080)


def test_rss_readings_are_plausible():
    rss = current_rss_bytes()
    assert 10e6 < rss < 1e12 and peak_rss_since_reset() >= rss * 0.5


def test_a_cap_that_does_not_fit_is_one_warning_naming_numbers_and_remedies():
    lines = []
    MemoryGuard.start(CPU, budget_gb=0.001, max_gaussians=2_000_000, count=1000, pixels=320 * 240,
                      announce=lines.append)
    [line] = lines
    assert "--pipeline.model.max-num-gaussians 2,000,000" in line and "budget of 0.00 GB" in line
    assert "mcmc" in line and "--downscale-factor" in line and "\n" not in line
    quiet = []
    MemoryGuard.start(CPU, budget_gb=1e6, max_gaussians=2_000_000, count=1000, pixels=320 * 240, announce=quiet.append)
    assert quiet == []


def test_growth_past_the_budget_is_capped_once_at_the_current_count():
    lines, caps = [], []
    guard = MemoryGuard(device=CPU, budget=1, pixels=320 * 240, last_count=100, announce=lines.append)
    assert guard.after_density_control(10, 100, caps.append) is None  # no growth: nothing to check
    line = guard.after_density_control(12, 150, caps.append)
    assert caps == [150] and guard.cap == 150 and lines == [line]
    assert "step 12" in line and "150 Gaussians" in line and "mcmc" in line
    assert guard.after_density_control(14, 150, caps.append) is None and caps == [150]  # said once
    roomy = MemoryGuard(device=CPU, budget=10**15, pixels=320 * 240, last_count=100, announce=lines.append)
    assert roomy.after_density_control(12, 150, caps.append) is None and roomy.cap is None


@pytest.mark.parametrize("limit", ["budget-flag", "machine-nearly-full"])
def test_a_training_under_a_small_memory_budget_finishes_with_a_checkpoint_and_one_line(limit, tmp_path, capsys,
                                                                                        monkeypatch):
    """Under a budget this process already exceeds (given with the flag, or the machine's: 1 MB left, no cgroup
    limit), the first growth stops density control from adding Gaussians: one line names the step, the count, the
    budget and the remedies; the run trains on and ends with its checkpoint, its count never above the cap (today such
    a run grows until the kernel kills it)."""
    monkeypatch.setenv("KC_SPLATFACTO_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("KC_DEBUG", raising=False)
    if limit == "machine-nearly-full":
        monkeypatch.setattr(memory, "_meminfo_available", lambda: 1_000_000)
        monkeypatch.setattr(memory, "_cgroup_room", lambda: None)
    budget = ["--machine.memory-budget-gb", "0.01"] if limit == "budget-flag" else []
    steps = 30
    code = kc_train.entrypoint([
        "splatfacto", "--data", "demo", "--output-dir", str(tmp_path / "out"), "--experiment-name", "e",
        "--timestamp", "t", "--max-num-iterations", str(steps), "--steps-per-eval-all-images", "0",
        "--logging.progress-bar", "False", "--final-lpips-nets", "--machine.device", "cpu", *budget,
        "--pipeline.model.steps-scale", "0.02", "--pipeline.model.num-downscales", "0", "demo", "--width", "64",
        "--height", "48"])
    captured = capsys.readouterr()
    assert code == 0, captured.err[-3000:]
    assert "Traceback" not in captured.err
    reached = [line for line in captured.err.splitlines() if "memory budget reached" in line]
    assert len(reached) == 1 and reached[0].startswith("kc-train: warning: memory budget reached at step "), reached
    assert "mcmc" in reached[0] and "--downscale-factor" in reached[0]
    run = tmp_path / "out" / "e" / "splatfacto" / "t"
    records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    [cap] = [r for r in records if r["kind"] == "memory_cap"]
    later = [r["gaussian_count"] for r in records if r["kind"] == "densify" and r["step"] > cap["step"]]
    assert all(count <= cap["gaussian_count"] for count in later)
    [checkpoint] = list_checkpoints(run / "nerfstudio_models")
    payload = load_checkpoint(checkpoint)
    assert payload["step"] == steps and payload["memory_cap"] == cap["gaussian_count"]
    assert payload["model"]["means"].shape[0] <= cap["gaussian_count"]


@pytest.mark.parametrize("budget", ["-1", "nan"])
def test_the_budget_is_checked_where_it_enters(budget, tmp_path, capsys):
    code = kc_train.entrypoint(["splatfacto", "--data", "demo", "--output-dir", str(tmp_path),
                                "--machine.memory-budget-gb", budget])
    assert code == 2 and "machine.memory_budget_gb" in capsys.readouterr().err
