"""Error against run time as the paired difference: at every evaluated step of a study, each method's difference to
the baseline run of the same scene and seed, with its 95 % interval, per scene and pooled, against steps and against
training time; and where along training (if anywhere) that interval excludes zero.

A study's answer read at its last step alone depends on where training was cut (a resolution switch or an opacity
reset just before it, a method that leads early and trails late); this reads it along the whole curve.

Conventions are the final-step tables' (:func:`~kc_splatfacto.analysis.report.paired_deltas`): PSNR in dB, SSIM and
LPIPS relative to the baseline (%); the interval is Student's t over pairs (ddof 1). ``pooled`` takes every (scene,
seed) pair of every scene as one draw (the final tables' ``all_pairs``). A curve keeps the steps that every one of
its pairs evaluated. Runs are paired at equal *step*; the time axis is where those steps fell, on average, for each
arm (a slower method's points lie further right than its baseline's).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

from kc_splatfacto.analysis.figures import pyplot, save_figure
from kc_splatfacto.analysis.report import TIME_KEYS, format_mean_interval, mean_interval, paired_difference

POOLED = "pooled"
"""the scene name of the curve over every scene's pairs"""
#: metric -> the label of its paired difference (:func:`~kc_splatfacto.analysis.report.paired_difference`)
DIFFERENCES = {"psnr": "ΔPSNR (dB)", "ssim": "ΔSSIM (%)", "lpips": "ΔLPIPS-alex (%)", "lpips_vgg": "ΔLPIPS-VGG (%)"}
ALONG_TRAINING_METRICS = ("psnr", "ssim", "lpips_vgg", "lpips")


def paired_along_training(rows: Sequence[dict], baseline: str, metric: str = "psnr",
                          time_key: str = "train_cpu_s") -> list[dict]:
    """Per method other than ``baseline`` and per scene (then ``pooled``), the paired difference of ``metric`` at each
    step that every pair of the curve evaluated.

    Args:
        rows: evaluation rows (``scene``, ``method``, ``seed``, ``step``, the metric, ``time_key``), as
            :func:`~kc_splatfacto.analysis.report.eval_rows` makes them.
    Returns:
        dicts with ``method``, ``scene``, ``metric``, ``pairs`` [(scene, seed)], and arrays [T]: ``steps``, ``mean``,
        ``low``, ``high`` (the 95 % t interval; the mean itself with a single pair), ``excludes_zero`` (bool),
        ``time`` and ``baseline_time`` (the mean ``time_key`` of the method's and of the baseline's runs there).
    """
    if metric not in DIFFERENCES:
        raise ValueError(f"metric must be one of {sorted(DIFFERENCES)}, got '{metric}'")
    index = {(r["scene"], r["method"], r["seed"], r["step"]): r for r in rows if r.get(metric) is not None}
    steps_of: dict[tuple, set[int]] = {}  # (scene, method, seed) -> the steps it evaluated
    for scene, method, seed, step in index:
        steps_of.setdefault((scene, method, seed), set()).add(step)
    methods = [m for m in dict.fromkeys(r["method"] for r in rows) if m != baseline]
    curves = []
    for method in methods:
        pairs = sorted({(scene, seed) for scene, m, seed in steps_of
                        if m == method and (scene, baseline, seed) in steps_of})
        scenes = list(dict.fromkeys(scene for scene, _ in pairs))
        groups = [(scene, [p for p in pairs if p[0] == scene]) for scene in scenes]
        if len(scenes) > 1:
            groups.append((POOLED, pairs))
        for scene, group in groups:
            steps = sorted(set.intersection(*(steps_of[(scene, method, seed)] & steps_of[(scene, baseline, seed)]
                                              for scene, seed in group)))
            curve = _curve(index, method, baseline, metric, group, steps, time_key) if steps else None
            if curve is not None:
                curves.append({"method": method, "scene": scene, **curve})
    return curves


def _curve(index: dict, method: str, baseline: str, metric: str, pairs: list[tuple], steps: list[int],
           time_key: str) -> dict:
    columns: dict[str, list] = {name: [] for name in ("mean", "low", "high", "excludes_zero", "time", "baseline_time")}
    for step in steps:
        ours = [index[(scene, method, seed, step)] for scene, seed in pairs]
        theirs = [index[(scene, baseline, seed, step)] for scene, seed in pairs]
        # (a relative difference to a baseline value of exactly 0 is undefined: that pair sits the step out)
        diffs = [d for a, b in zip(ours, theirs) if (d := paired_difference(metric, a[metric], b[metric])) is not None]
        mean = float(np.mean(diffs))
        low, high = mean_interval(diffs) or (mean, mean)
        columns["mean"].append(mean)
        columns["low"].append(low)
        columns["high"].append(high)
        columns["excludes_zero"].append(len(diffs) > 1 and (low > 0 or high < 0))
        columns["time"].append(_mean_time(ours, time_key))
        columns["baseline_time"].append(_mean_time(theirs, time_key))
    return {"metric": metric, "pairs": pairs, "steps": np.array(steps),
            **{name: np.array(values) for name, values in columns.items()}}


def _mean_time(rows: Sequence[dict], time_key: str) -> float:
    values = [r.get(time_key) for r in rows]
    return float("nan") if any(v is None for v in values) else float(np.mean(np.asarray(values, dtype=np.float64)))


# ----------------------------------------------------------------------------------------------- figure
def plot_along_training(curves: Sequence[dict], method: str, baseline: str, path: str | Path,
                        time_key: str = "train_cpu_s") -> Path | None:
    """PNG for one method: a row per metric (its paired difference), against steps (left) and against training time
    (right); a thin line per scene, the pooled mean thick with its 95 % band, filled markers where the pooled interval
    excludes zero. None when the method has no curve."""
    mine = [c for c in curves if c["method"] == method]
    metrics = [m for m in ALONG_TRAINING_METRICS if any(c["metric"] == m and len(c["steps"]) > 1 for c in mine)]
    if not metrics:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(len(metrics), 2, figsize=(12, 3.2 * len(metrics)), squeeze=False)
    scenes = list(dict.fromkeys(c["scene"] for c in mine if c["scene"] != POOLED))
    colors = {scene: plt.get_cmap("tab10")(i % 10) for i, scene in enumerate(scenes)}
    for row, metric in zip(axes, metrics):
        for ax, x_key in zip(row, ("steps", "time")):
            for curve in (c for c in mine if c["metric"] == metric):
                x = curve[x_key]
                if curve["scene"] == POOLED:
                    ax.plot(x, curve["mean"], "-", color="k", lw=2, label=f"pooled ({len(curve['pairs'])} pairs)")
                    ax.fill_between(x, curve["low"], curve["high"], color="k", alpha=0.15, lw=0)
                    hits = curve["excludes_zero"]
                    ax.plot(x[hits], curve["mean"][hits], "o", color="k", ms=5)
                    ax.plot(x[~hits], curve["mean"][~hits], "o", mfc="white", color="k", ms=4)
                else:
                    label = f"{curve['scene']} ({len(curve['pairs'])})"
                    ax.plot(x, curve["mean"], "-", color=colors[curve["scene"]], lw=1, alpha=0.8, label=label)
            ax.axhline(0.0, color="grey", lw=0.8)
            ax.set_ylabel(f"{DIFFERENCES[metric]}\n{method} - {baseline}")
            ax.grid(True, alpha=0.3)
        row[0].set_xlabel("training step")
        row[1].set_xlabel(TIME_KEYS[time_key])
        row[0].legend(fontsize=7)
    axes[0][0].set_title("paired at equal step (same scene and seed): mean, 95 % t band (pooled);\n"
                         "filled: the pooled interval excludes zero", fontsize=9)
    axes[0][1].set_title("the same pairs (equal step) drawn at the mean training time of the method's runs there",
                         fontsize=9)
    return save_figure(fig, path, dpi=110)


def plot_pooled_psnr(curves: Sequence[dict], baseline: str, path: str | Path,
                     time_key: str = "train_cpu_s") -> Path | None:
    """PNG of the study against training time: per method, its pooled PSNR curve of :func:`paired_along_training`
    (every (scene, seed) pair; a one-scene study's scene curve) with its 95 % t band, at the mean training time the
    method's runs had reached at each step (so a slower method's curve is shifted right), and the ratio of the mean
    times at each step. None when nothing pairs."""
    chosen = []
    for method in dict.fromkeys(c["method"] for c in curves):
        psnr = [c for c in curves if c["method"] == method and c["metric"] == "psnr"]
        chosen += [c for c in psnr if c["scene"] == POOLED] or psnr[:1]
    if not chosen:
        return None
    plt = pyplot()
    fig, (ax, cost) = plt.subplots(1, 2, figsize=(12, 4.2))
    for i, curve in enumerate(chosen):
        color = plt.get_cmap("tab10")((i + 1) % 10)
        scenes = sorted({p[0] for p in curve["pairs"]})
        label = f"{curve['method']} ({len(curve['pairs'])} pairs, {len(scenes)} scenes)"
        ax.plot(curve["time"], curve["mean"], "-o", ms=3, color=color, label=label)
        ax.fill_between(curve["time"], curve["low"], curve["high"], color=color, alpha=0.2, lw=0)
        cost.plot(curve["steps"], curve["time"] / curve["baseline_time"], "-o", ms=3, color=color,
                  label=curve["method"])
    ax.axhline(0.0, color="k", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel(f"{TIME_KEYS[time_key]}, mean over the method's runs")
    ax.set_ylabel(f"PSNR - {baseline} (dB, same scene and seed)")
    ax.set_title("pooled over scenes: paired PSNR difference at equal step (same scene and seed; mean, 95 % t band\n"
                 "over pairs), drawn at the mean training time the method's runs had reached at that step", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    cost.axhline(1.0, color="k", lw=0.8)
    cost.set_xlabel("training step")
    cost.set_ylabel(f"mean time / {baseline}'s, same step")
    cost.set_title(f"cost: ratio of the mean {TIME_KEYS[time_key].split(' (')[0]}s (not a mean of per-pair ratios)",
                   fontsize=9)
    cost.grid(True, alpha=0.3)
    cost.legend(fontsize=8)
    return save_figure(fig, path, dpi=120)


# ----------------------------------------------------------------------------------------------- tables
def _cell(curve: dict, i: int, digits: int) -> str:
    interval = (float(curve["low"][i]), float(curve["high"][i])) if len(curve["pairs"]) > 1 else None  # one pair: none
    text = format_mean_interval(float(curve["mean"][i]), interval, digits)
    return f"**{text}**" if curve["excludes_zero"][i] else text


def markdown_along_training(curves: Sequence[dict], baseline: str) -> str:
    """Per method: the pooled paired differences at every evaluated step (time ratio to the baseline, each metric's
    mean and interval, bold where the interval excludes zero), then per scene and metric the steps at which the
    interval excludes zero and the endpoint."""
    lines = []
    for method in dict.fromkeys(c["method"] for c in curves):
        mine = [c for c in curves if c["method"] == method]
        scenes = list(dict.fromkeys(c["scene"] for c in mine))
        headline = POOLED if POOLED in scenes else scenes[0]
        top = {c["metric"]: c for c in mine if c["scene"] == headline}
        if "psnr" not in top:
            continue
        metrics = [m for m in ALONG_TRAINING_METRICS if m in top]
        lines += [f"### {method} - {baseline} along training ({headline}, {len(top['psnr']['pairs'])} pairs; "
                  "paired at equal step; mean [95 % t]; bold: the interval excludes zero)", "",
                  "| step | time ratio | " + " | ".join(DIFFERENCES[m] for m in metrics) + " |",
                  "|---|---|" + "---|" * len(metrics)]
        psnr = top["psnr"]
        for i, step in enumerate(psnr["steps"]):
            ratio = psnr["time"][i] / psnr["baseline_time"][i]
            cells = []
            for metric in metrics:
                where = np.flatnonzero(top[metric]["steps"] == step)
                cells.append(_cell(top[metric], int(where[0]), 2 if metric == "psnr" else 1) if where.size else "")
            lines.append(f"| {int(step)} | {ratio:.3f}x | " + " | ".join(cells) + " |")
        lines += ["", f"Where the interval excludes zero ({method} - {baseline}), per scene and metric, and the "
                      "endpoint:", "", "| scene | metric | pairs | steps where the interval excludes zero | "
                                       "endpoint (step: mean [95 % t]) |", "|---|---|---|---|---|"]
        for scene in scenes:
            for curve in (c for c in mine if c["scene"] == scene):
                digits = 2 if curve["metric"] == "psnr" else 1
                hits = [f"{int(s)} ({float(m):+.{digits}f})" for s, m, hit in
                        zip(curve["steps"], curve["mean"], curve["excludes_zero"]) if hit]
                end = f"{int(curve['steps'][-1])}: {_cell(curve, len(curve['steps']) - 1, digits)}"
                lines.append(f"| {scene} | {DIFFERENCES[curve['metric']]} | {len(curve['pairs'])} | "
                             f"{', '.join(hits) or 'none'} | {end} |")
        lines.append("")
    return "\n".join(lines)


def write_along_training(rows: Sequence[dict], out_dir: str | Path, baseline: str,
                         time_key: str = "train_cpu_s") -> dict[str, Path]:
    """``along_training.md``, ``along_training.json``, ``along_training_<method>.png`` and ``pooled_psnr_vs_time.png``
    under ``out_dir`` (nothing when no method pairs with ``baseline``). Returns the paths by name."""
    curves = [c for metric in ALONG_TRAINING_METRICS for c in paired_along_training(rows, baseline, metric, time_key)]
    if not curves:
        return {}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"along_training": out_dir / "along_training.md", "along_training_json": out_dir / "along_training.json"}
    paths["along_training"].write_text(markdown_along_training(curves, baseline))
    serial = [{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in c.items()} for c in curves]
    paths["along_training_json"].write_text(json.dumps(serial, indent=1))
    for method in dict.fromkeys(c["method"] for c in curves):
        png = plot_along_training(curves, method, baseline, out_dir / f"along_training_{method}.png", time_key)
        if png is not None:
            paths[f"along_training_{method}"] = png
    if any(r.get(time_key) is not None for r in rows):
        pooled = plot_pooled_psnr(curves, baseline, out_dir / "pooled_psnr_vs_time.png", time_key)
        if pooled is not None:
            paths["plot_pooled"] = pooled
    return paths
