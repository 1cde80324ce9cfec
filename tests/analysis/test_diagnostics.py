"""Wavelet diagnostics: subband differences against PyWavelets, the error-ratio map's meaning, valid PNGs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import pywt
import torch

from kc_splatfacto.analysis import diagnostics


def _images(seed: int = 0, size: tuple[int, int] = (48, 64)):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0, 1, size=(*size, 3))
    gt = cv2.GaussianBlur(gt, (0, 0), 1.0)
    pred = cv2.GaussianBlur(gt, (0, 0), 2.0)  # a smoothed render: missing detail
    return torch.tensor(pred), torch.tensor(gt)


def test_coarse_differences_match_pywavelets():
    pred, gt = _images()
    diffs = diagnostics.coarse_subband_differences(pred, gt, wave="db3", levels=2)
    ref = []
    for image in (pred.numpy(), gt.numpy()):
        per_channel = [pywt.wavedec2(image[..., c], "db3", mode="symmetric", level=2)[1] for c in range(3)]
        ref.append(np.mean([np.stack(bands) for bands in per_channel], axis=0))  # [3, h, w], channel mean
    np.testing.assert_allclose(diffs, ref[0] - ref[1], atol=1e-9)


def test_error_ratio_marks_wavelet_and_pixel_regions():
    gt = np.full((64, 64, 3), 0.5)
    gt[8:24, 8:56] += 0.3 * ((np.arange(48) % 2) * 2 - 1)[:, None]  # fine stripes: pure high-frequency content
    pred = gt.copy()
    pred[8:24, 8:56] = 0.5  # render lost the stripes: a detail error
    pred[40:60, 8:56] += 0.1  # flat brightness offset: a pixel error without detail change
    ratio = diagnostics.wavelet_pixel_error_ratio(torch.tensor(pred), torch.tensor(gt), levels=2)
    assert ratio.shape == (64, 64) and np.isfinite(ratio).all()
    assert ratio[12:20, 16:48].mean() > 0  # wavelet-emphasized (red)
    assert ratio[46:56, 16:48].mean() < -2  # pixel-emphasized (blue): a flat offset has no detail error


def test_identical_images_are_finite():
    pred, _ = _images()
    ratio = diagnostics.wavelet_pixel_error_ratio(pred, pred, levels=2)
    assert np.isfinite(ratio).all() and np.abs(ratio).max() < 1e-9


def test_view_png_decodes(tmp_path):
    pred, gt = _images(1)
    path = diagnostics.save_view_diagnostics(pred, gt, tmp_path / "view.png", levels=2, title="t")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and image.shape[0] > 200 and image.std() > 0


def test_kurtosis_history_plot(tmp_path):
    records = [{"kind": "eval", "step": 0, "psnr": 1.0}]
    for step in range(0, 100, 10):
        records.append({"kind": "train", "step": step, "kurtosis_render": [float(step)] * 9, "kurtosis_gt": [3.0] * 9})
        records.append({"kind": "train", "step": step + 1, "main_loss": 0.1})
    steps, render, gt = diagnostics.kurtosis_history(records)
    assert steps.tolist() == list(range(0, 100, 10)) and render.shape == gt.shape == (10, 9)
    path = diagnostics.plot_kurtosis_history(records, tmp_path / "k.png")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and image.std() > 0
    assert diagnostics.band_labels(9)[:4] == ["L1 LH", "L1 HL", "L1 HH", "L2 LH"]


def test_kurtosis_history_keeps_the_finest_training_resolution():
    # Splatfacto's resolution schedule: 2 levels at 1/4 resolution, then 3 levels at 1/2 and at full resolution;
    # level j of a downscaled image is another scale, so only the full-resolution records make the history
    records = []
    for step, downscale, bands in [(10, 4, 6), (20, 4, 6), (30, 2, 9), (40, 1, 9), (50, 1, 9)]:
        records.append({"kind": "train", "step": step, "train_downscale": downscale,
                        "kurtosis_render": [float(step)] * bands, "kurtosis_gt": [1.0] * bands})
    steps, render, gt = diagnostics.kurtosis_history(records)
    assert steps.tolist() == [40, 50] and render.shape == gt.shape == (2, 9)
    assert render[:, 0].tolist() == [40.0, 50.0]


def test_bad_inputs():
    with pytest.raises(ValueError, match="kurtosis_render"):
        diagnostics.kurtosis_history([{"kind": "train", "step": 1}])
    bad = torch.zeros(8, 8, 3)
    bad[0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="pred"):
        diagnostics.wavelet_pixel_error_ratio(bad, torch.zeros(8, 8, 3), levels=1)
    with pytest.raises(ValueError, match="H,W,3"):
        diagnostics.coarse_subband_differences(torch.zeros(8, 8), torch.zeros(8, 8), levels=1)


def test_running_mean_and_gap_against_numpy(tmp_path):
    values = np.random.default_rng(3).normal(size=(20, 2))
    smoothed = diagnostics.running_mean(values, 4)
    for t in range(20):
        np.testing.assert_allclose(smoothed[t], values[max(0, t - 3):t + 1].mean(axis=0), rtol=1e-12)
    records = [{"kind": "train", "step": s, "kurtosis_render": [float(s)] * 6, "kurtosis_gt": [1.0, 2.0, 3.0] * 2}
               for s in range(10)]
    steps, gap = diagnostics.kurtosis_gap(records)
    np.testing.assert_allclose(gap[:, 0], [np.mean(np.abs(s - np.array([1.0, 2.0, 3.0]))) for s in range(10)])
    path = diagnostics.plot_kurtosis_gap_comparison({"a": records, "b": records[::2]}, tmp_path / "gap.png", window=3)
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and image.std() > 0


def test_the_gap_comparison_draws_methods_of_different_level_counts(tmp_path):
    # a two-level method (splatfacto-lowpass's Haar) beside a three-level one: each drawn at the levels it has
    three = [{"kind": "train", "step": s, "kurtosis_render": [float(s)] * 9, "kurtosis_gt": [1.0] * 9} for s in range(8)]
    two = [{"kind": "train", "step": s, "kurtosis_render": [float(s)] * 6, "kurtosis_gt": [2.0] * 6} for s in range(8)]
    for order in ({"three": three, "two": two}, {"two": two, "three": three}):
        path = diagnostics.plot_kurtosis_gap_comparison(order, tmp_path / "gap.png", window=3)
        image = cv2.imread(str(path), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[1] > image.shape[0] * 3  # three panels side by side
