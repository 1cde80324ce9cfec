"""Wavelet diagnostics in the spirit of the paper's figures.

- :func:`plot_kurtosis_history`: per-band excess kurtosis of the render and of the ground truth over training, read
  from the ``kurtosis_render`` / ``kurtosis_gt`` lists the trainer logs on logging steps (one value per detail band,
  channel-averaged, in ``band_kurtosis`` order: levels finest first, orientations LH, HL, HH within a level).
- :func:`coarse_subband_differences`: signed differences ``pred - gt`` of the coarsest level's LH/HL/HH coefficients.
- :func:`wavelet_pixel_error_ratio`: where the wavelet detail error is large relative to the pixel L1 error. Both maps
  are normalized by their own mean, so the ratio is 1 where both errors are "as usual"; the log2 of the ratio is
  positive (red) in wavelet-emphasized regions and negative (blue) in pixel-emphasized ones.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterable

import cv2
import numpy as np
import torch

from kc_splatfacto.analysis.figures import pyplot, save_figure
from kc_splatfacto.losses.wavelets import dwt2

#: Orientation names of (cH, cV, cD), the paper's naming.
ORIENTATIONS = ("LH", "HL", "HH")
#: Added to both normalized error maps before the ratio: keeps the ratio finite where both errors vanish.
RATIO_EPS = 1e-3


def band_labels(num_bands: int) -> list[str]:
    """Labels for ``band_kurtosis`` values: 'L1 LH', 'L1 HL', ... (level 1 = finest)."""
    if num_bands % 3:
        raise ValueError(f"band count {num_bands} is not a multiple of 3 (three orientations per level)")
    return [f"L{level + 1} {o}" for level in range(num_bands // 3) for o in ORIENTATIONS]


def kurtosis_history(records: Iterable[dict]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps [T], render kurtosis [T, B] and GT kurtosis [T, B] from the train records that carry them.

    Under Splatfacto's resolution schedule the early records are of a downscaled image, whose level j is another
    scale than the full-resolution level j (and fewer levels fit): only the records at the run's finest training
    resolution (the smallest ``train_downscale`` logged) are returned.
    """
    carrying = [
        r for r in records
        if r.get("kind", "train") == "train" and r.get("kurtosis_render") is not None and r.get("kurtosis_gt") is not None
    ]
    downscales = [r["train_downscale"] for r in carrying if r.get("train_downscale") is not None]
    if downscales:
        finest = min(downscales)
        carrying = [r for r in carrying if r.get("train_downscale", finest) == finest]
    steps, render, gt = [], [], []
    for record in carrying:
        steps.append(int(record["step"]))
        render.append([float(v) for v in record["kurtosis_render"]])
        gt.append([float(v) for v in record["kurtosis_gt"]])
    if not steps:
        raise ValueError(
            "no train record carries 'kurtosis_render'/'kurtosis_gt' (they are logged on logging steps only; "
            "train for more steps than the logging interval)"
        )
    lengths = {len(r) for r in render} | {len(g) for g in gt}
    if len(lengths) != 1:
        raise ValueError(f"kurtosis lists have varying lengths {sorted(lengths)} across records")
    return np.array(steps), np.array(render, dtype=np.float64), np.array(gt, dtype=np.float64)


def plot_kurtosis_history(records: Iterable[dict], path: str | Path, title: str = "") -> Path:
    """PNG: one panel per level, render (solid) and ground truth (dashed) kurtosis of each orientation over steps."""
    plt = pyplot()

    steps, render, gt = kurtosis_history(records)
    levels = render.shape[1] // 3
    labels = band_labels(render.shape[1])
    fig, axes = plt.subplots(1, levels, figsize=(4.2 * levels, 3.4), squeeze=False)
    for level in range(levels):
        ax = axes[0, level]
        for o in range(3):
            b = 3 * level + o
            color = plt.get_cmap("tab10")(o)
            ax.plot(steps, render[:, b], "-", color=color, label=f"{labels[b]} render")
            ax.plot(steps, gt[:, b], "--", color=color, label=f"{labels[b]} GT")
        ax.set_title(f"level {level + 1} ({'finest' if level == 0 else 'coarser'})", fontsize=9)
        ax.set_xlabel("step")
        ax.set_ylabel("excess kurtosis")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=6, ncol=2)
    if title:
        fig.suptitle(title, fontsize=10)
    path = save_figure(fig, path, dpi=110)
    return path


def running_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing running mean over axis 0 (the first ``window - 1`` entries average what exists so far)."""
    values = np.asarray(values, dtype=np.float64)
    window = max(int(window), 1)
    cumulative = np.cumsum(np.concatenate([np.zeros((1, *values.shape[1:])), values]), axis=0)
    index = np.arange(1, values.shape[0] + 1)
    start = np.maximum(index - window, 0)
    counts = (index - start).reshape(-1, *([1] * (values.ndim - 1)))
    return (cumulative[index] - cumulative[start]) / counts


def kurtosis_gap(records: Iterable[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Steps [T] and the per-level gap [T, J]: mean over the three orientations of |k_render - k_gt|."""
    steps, render, gt = kurtosis_history(records)
    gap = np.abs(render - gt)
    return steps, gap.reshape(gap.shape[0], -1, 3).mean(axis=2)


def plot_kurtosis_gap_comparison(records_by_method: dict[str, Iterable[dict]], path: str | Path, window: int = 10,
                                 title: str = "") -> Path:
    """PNG: per level, the running mean (``window`` log records) of the render-vs-GT kurtosis gap, one curve per
    method. The logged kurtosis is that of the step's training image, so single records are noisy; the running mean
    shows the trend."""
    plt = pyplot()

    gaps = {method: kurtosis_gap(records) for method, records in records_by_method.items()}
    if not gaps:
        raise ValueError("plot_kurtosis_gap_comparison: no method given")
    # methods may decompose into different numbers of levels (another wavelet or level count): each is drawn at the
    # levels it has
    levels = max(gap.shape[1] for _, gap in gaps.values())
    fig, axes = plt.subplots(1, levels, figsize=(4.2 * levels, 3.4), squeeze=False)
    for level in range(levels):
        ax = axes[0, level]
        for i, (method, (steps, gap)) in enumerate(gaps.items()):
            if level >= gap.shape[1]:
                continue
            ax.plot(steps, running_mean(gap[:, level], window), color=plt.get_cmap("tab10")(i), label=method)
        ax.set_title(f"level {level + 1}: |kurtosis render - GT| (running mean of {window})", fontsize=8)
        ax.set_xlabel("step")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    if title:
        fig.suptitle(title, fontsize=10)
    path = save_figure(fig, path, dpi=110)
    return path


def _to_bchw(image: torch.Tensor | np.ndarray, name: str) -> torch.Tensor:
    tensor = torch.as_tensor(np.asarray(image) if not isinstance(image, torch.Tensor) else image).detach()
    if tensor.ndim != 3 or tensor.shape[-1] not in (1, 3):
        raise ValueError(f"{name}: expected an [H,W,3] (or [H,W,1]) image, got {tuple(tensor.shape)}")
    if not torch.isfinite(tensor).all():
        raise ValueError(f"{name}: image has NaN or Inf values")
    return tensor.to(torch.float64).permute(2, 0, 1)[None]


def coarse_subband_differences(
    pred: torch.Tensor, gt: torch.Tensor, wave: str = "db3", levels: int = 3, mode: str = "symmetric"
) -> np.ndarray:
    """Signed channel-mean differences of the coarsest available level's detail subbands.

    Args:
        pred, gt: [H,W,3] images in [0,1].
    Returns:
        [3, h, w] float64: (LH, HL, HH) of ``pred`` minus those of ``gt`` at the coarsest level.
    """
    p = dwt2(_to_bchw(pred, "pred"), wave=wave, levels=levels, mode=mode)
    g = dwt2(_to_bchw(gt, "gt"), wave=wave, levels=levels, mode=mode)
    diff = (p.details[-1] - g.details[-1]).mean(dim=1)[0]  # [3, h, w]
    return diff.numpy()


def wavelet_pixel_error_ratio(
    pred: torch.Tensor, gt: torch.Tensor, wave: str = "db3", levels: int = 3, mode: str = "symmetric"
) -> np.ndarray:
    """log2 of (normalized wavelet detail error) / (normalized pixel L1 error), per pixel.

    The wavelet error map is, per level, sum over orientations and mean over channels of |d_pred - d_gt|, resized
    to the image size (bilinear) and averaged over levels; the pixel map is the channel mean of |pred - gt|. Each
    map is divided by its own mean before the ratio, and ``RATIO_EPS`` is added to both.

    Returns:
        [H, W] float64; > 0 where wavelet errors dominate, < 0 where pixel errors dominate.
    """
    p_img, g_img = _to_bchw(pred, "pred"), _to_bchw(gt, "gt")
    height, width = p_img.shape[-2:]
    p = dwt2(p_img, wave=wave, levels=levels, mode=mode)
    g = dwt2(g_img, wave=wave, levels=levels, mode=mode)
    wave_err = np.zeros((height, width))
    for dp, dg in zip(p.details, g.details):
        level_err = (dp - dg).abs().sum(dim=2).mean(dim=1)[0].numpy()  # [h, w]
        wave_err += cv2.resize(level_err, (width, height), interpolation=cv2.INTER_LINEAR)
    wave_err /= max(len(p.details), 1)
    pixel_err = (p_img - g_img).abs().mean(dim=1)[0].numpy()
    wave_norm = wave_err / max(float(wave_err.mean()), 1e-12)
    pixel_norm = pixel_err / max(float(pixel_err.mean()), 1e-12)
    return np.log2((wave_norm + RATIO_EPS) / (pixel_norm + RATIO_EPS))


def save_view_diagnostics(
    pred: torch.Tensor, gt: torch.Tensor, path: str | Path, wave: str = "db3", levels: int = 3, title: str = ""
) -> Path:
    """PNG for one test view. Top row: signed coarse-level LH/HL/HH differences (pred - GT, symmetric colour range).
    Bottom row: render, ground truth, log2 wavelet-vs-pixel error ratio (red wavelet-, blue pixel-emphasized)."""
    plt = pyplot()

    diffs = coarse_subband_differences(pred, gt, wave, levels)
    ratio = wavelet_pixel_error_ratio(pred, gt, wave, levels)
    fig, axes = plt.subplots(2, 3, figsize=(12, 6.5))
    limit = max(float(np.abs(diffs).max()), 1e-6)
    for o in range(3):
        im = axes[0, o].imshow(diffs[o], cmap="seismic", vmin=-limit, vmax=limit)
        axes[0, o].set_title(f"coarsest {ORIENTATIONS[o]}: pred - GT", fontsize=9)
        fig.colorbar(im, ax=axes[0, o], fraction=0.046)
    axes[1, 0].imshow(np.clip(np.asarray(torch.as_tensor(pred).detach().cpu()), 0, 1))
    axes[1, 0].set_title("render", fontsize=9)
    axes[1, 1].imshow(np.clip(np.asarray(torch.as_tensor(gt).detach().cpu()), 0, 1))
    axes[1, 1].set_title("ground truth", fontsize=9)
    rlim = max(float(np.abs(ratio).max()), 1e-6)
    im = axes[1, 2].imshow(ratio, cmap="bwr", vmin=-rlim, vmax=rlim)
    axes[1, 2].set_title("log2 wavelet / pixel error (red: wavelet)", fontsize=9)
    fig.colorbar(im, ax=axes[1, 2], fraction=0.046)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    path = save_figure(fig, path, dpi=100)
    return path
