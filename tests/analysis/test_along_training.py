"""The paired difference along training against numpy and scipy on made-up rows: per scene and pooled, absolute
for PSNR and relative for SSIM/LPIPS, Student t intervals, the steps every pair evaluated, where the interval
excludes zero; the table, the JSON and the figure are written."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from kc_splatfacto.analysis.along_training import POOLED, paired_along_training, write_along_training

STEPS = (100, 200, 300)
EFFECT = {"A": {100: 0.0, 200: 0.5, 300: -0.3}, "B": {100: 0.1, 200: 0.4, 300: 0.0}}
NOISE = {("A", 0): -0.05, ("A", 1): 0.04, ("A", 2): 0.02, ("B", 0): 0.03, ("B", 1): -0.06}


def _rows(drop: tuple | None = None) -> list[dict]:
    rows = []
    for (scene, seed), noise in NOISE.items():
        for step in STEPS:
            base = 20.0 + seed + step / 100
            arms = (("base", base, 0.5 + 0.01 * seed),
                    ("kc", base + EFFECT[scene][step] + noise * step / 100, 0.5 + 0.01 * seed + noise / 10))
            for method, psnr, ssim in arms:
                if drop == (scene, method, seed, step):
                    continue
                rows.append({"scene": scene, "method": method, "seed": seed, "step": step, "psnr": psnr, "ssim": ssim,
                             "lpips": None, "train_cpu_s": step * (1.1 if method == "kc" else 1.0)})
    return rows


def _t_interval(values: list[float]) -> tuple[float, float, float]:
    values = np.asarray(values)
    half = stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values))
    return values.mean(), values.mean() - half, values.mean() + half


def test_per_scene_and_pooled_psnr_differences_match_numpy_and_scipy():
    rows = _rows()
    curves = {c["scene"]: c for c in paired_along_training(rows, "base", "psnr")}
    assert set(curves) == {"A", "B", POOLED} and len(curves[POOLED]["pairs"]) == 5
    for scene, curve in curves.items():
        pairs = [p for p in NOISE if scene in (POOLED, p[0])]
        assert curve["pairs"] == sorted(pairs) and list(curve["steps"]) == list(STEPS)
        for i, step in enumerate(STEPS):
            diffs = [EFFECT[s][step] + NOISE[(s, seed)] * step / 100 for s, seed in pairs]
            mean, low, high = _t_interval(diffs)
            assert curve["mean"][i] == pytest.approx(mean, abs=1e-12)
            assert (curve["low"][i], curve["high"][i]) == pytest.approx((low, high), abs=1e-12)
            assert curve["excludes_zero"][i] == (low > 0 or high < 0)
        assert list(curve["time"]) == pytest.approx([1.1 * s for s in STEPS])
        assert list(curve["baseline_time"]) == pytest.approx(list(STEPS))
    assert list(curves[POOLED]["excludes_zero"]) == [False, True, False]  # +0.45 at step 200 over all five pairs


def test_ssim_is_relative_and_a_step_one_pair_lacks_is_left_out():
    rows = _rows(drop=("B", "kc", 1, 200))
    curves = {c["scene"]: c for c in paired_along_training(rows, "base", "ssim")}
    assert list(curves["B"]["steps"]) == [100, 300] and list(curves[POOLED]["steps"]) == [100, 300]
    assert list(curves["A"]["steps"]) == list(STEPS)
    diffs = [100 * (NOISE[p] / 10) / (0.5 + 0.01 * p[1]) for p in sorted(NOISE)]
    assert curves[POOLED]["mean"][0] == pytest.approx(np.mean(diffs), abs=1e-12)


def test_the_files_are_written(tmp_path):
    paths = write_along_training(_rows(), tmp_path, "base")
    table = paths["along_training"].read_text()
    assert "### kc - base along training (pooled, 5 pairs" in table
    assert "| 200 | 1.100x | **+0.45 [" in table  # (3 x 0.5 + 2 x 0.4 - 0.04) / 5
    assert "| A | ΔPSNR (dB) | 3 |" in table
    stored = json.loads(paths["along_training_json"].read_text())
    assert {(c["scene"], c["metric"]) for c in stored} >= {(POOLED, "psnr"), ("A", "ssim")}
    assert paths["along_training_kc"].stat().st_size > 10_000
    assert write_along_training([r for r in _rows() if r["method"] == "base"], tmp_path / "none", "base") == {}
