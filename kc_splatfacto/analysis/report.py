"""Error against run time: aggregate many runs' ``metrics.jsonl`` into tables, plots and a markdown summary.

Input: the evaluation records every run writes (``{"kind": "eval", "step", "elapsed_s", "train_s", "psnr", "ssim",
"lpips", ...}``), labelled with the run's scene, method and seed. Output:
- a flat table of every evaluation (CSV / JSON),
- per metric, a PNG of the metric against training seconds, one curve per method (mean over seeds, shaded min-max
  spread over seeds), one panel per scene,
- a markdown table of the final evaluation of every method with the paper's kind of relative deltas against a
  baseline method (dB for PSNR, % for SSIM and LPIPS, x for time),
- per scene, the gradient shares of the loss terms against step (:func:`plot_gradient_shares`; a term whose share
  stays far below 1 % does next to nothing at its weight).

Time axis: ``train_s`` (seconds spent in training steps, evaluation excluded) by default, so methods are compared
on what their training costs, not on how often they were evaluated. A run's first step also holds one-time start-up
work that is no cost of its method (numba compiling the CPU kernels into its on-disk cache on the first use of a
source tree: 100-120 s, in whichever runs a study happens to start first); :func:`clock_offsets` takes it out.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from kc_splatfacto.analysis.figures import pyplot, save_figure

#: Metrics reported, with the direction that is better.
METRICS = {"psnr": "higher", "ssim": "higher", "lpips": "lower"}
METRIC_LABELS = {"psnr": "PSNR (dB)", "ssim": "SSIM", "lpips": "LPIPS"}
#: Columns of the flat evaluation table, in order.
EVAL_COLUMNS = (
    "scene", "method", "seed", "step", "elapsed_s", "train_s", "train_cpu_s", "psnr", "ssim", "lpips", "lpips_net",
    "lpips_vgg", "num_images", "run_dir", "cpu",
)
#: Final-evaluation metrics compared in the paired tables (``lpips_vgg``: the last evaluation only).
PAIRED_METRICS = {"psnr": "psnr_db", "ssim": "ssim_pct", "lpips": "lpips_pct", "lpips_vgg": "lpips_vgg_pct"}
TIME_KEYS = {
    "train_s": "training time (s, evaluation excluded)",
    "train_cpu_s": "training CPU time (s, all threads, evaluation excluded)",
    "elapsed_s": "wall-clock time (s)",
}
DEFAULT_TIME_KEY = "train_s"
INTERVAL_LEVEL = 0.95
"""two-sided confidence level of the interval on a mean paired difference (Student t over seeds)"""


def _number(value) -> float | None:
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def clock_offsets(records: Sequence[dict]) -> dict[str, float]:
    """Seconds to take off each clock of a run (``train_s``, ``train_cpu_s``; ``elapsed_s`` loses ``train_s``'s)
    so that its first step costs what the steps after it cost: the clock at the first logged step ``s0`` minus
    ``s0`` times the per-step rate between the first two logged steps. 0 for a run with fewer than two logged steps
    or no such clock.

    The first step is where one-time start-up lands (kernel compilation), which would otherwise be charged to the
    run's method."""
    logged = sorted((r for r in records if r.get("kind") in ("train", "eval") and "step" in r), key=lambda r: r["step"])
    offsets = {"train_s": 0.0, "train_cpu_s": 0.0}
    for key in offsets:
        timed = [r for r in logged if _number(r.get(key)) is not None]
        first = timed[0] if timed else None
        later = next((r for r in timed if r["step"] > first["step"]), None) if first else None
        if first is None or later is None:
            continue
        rate = (float(later[key]) - float(first[key])) / (later["step"] - first["step"])
        offsets[key] = max(0.0, float(first[key]) - first["step"] * max(rate, 0.0))
    offsets["elapsed_s"] = offsets["train_s"]
    return offsets


def _minus(value: float | None, offset: float) -> float | None:
    return None if value is None else value - offset


def eval_rows(records: Iterable[dict], scene: str, method: str, seed: int, run_dir: str | Path = "",
              cpu: str = "") -> list[dict]:
    """The evaluation records of one run as flat rows (:data:`EVAL_COLUMNS`), sorted by step, one per step; clocks
    without the run's start-up (:func:`clock_offsets`). ``cpu``: the kind(s) of CPU the run trained on (what the
    kernels' rounding depends on; ``""`` when not recorded), so pairs that mixed machines can be named."""
    records = list(records)
    offset = clock_offsets(records)
    rows: list[dict[str, Any]] = []
    for record in records:
        if record.get("kind") != "eval":
            continue
        for key in ("step", "elapsed_s", "train_s"):
            if key not in record:
                raise KeyError(f"eval record of {method}/{scene}/seed {seed} has no '{key}': {record}")
        rows.append(
            {
                "scene": scene,
                "method": method,
                "seed": int(seed),
                "step": int(record["step"]),
                "elapsed_s": float(record["elapsed_s"]) - offset["elapsed_s"],
                "train_s": float(record["train_s"]) - offset["train_s"],
                "train_cpu_s": _minus(_number(record.get("train_cpu_s")), offset["train_cpu_s"]),
                "psnr": _number(record.get("psnr")),
                "ssim": _number(record.get("ssim")),
                "lpips": _number(record.get("lpips")),
                "lpips_net": record.get("lpips_net") if record.get("lpips") is not None else None,
                "lpips_vgg": _number(record.get("lpips_vgg")),
                "num_images": record.get("num_images"),
                "run_dir": str(run_dir),
                "cpu": cpu,
            }
        )
    # one row per step: a log continued after an interruption may repeat a step; the later record wins
    rows = list({row["step"]: row for row in rows}.values())
    rows.sort(key=lambda row: row["step"])
    return rows


def write_rows_csv(rows: Sequence[dict], path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(EVAL_COLUMNS), extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({key: ("" if row.get(key) is None else row.get(key)) for key in EVAL_COLUMNS})
    return path


def read_rows_csv(path: str | Path) -> list[dict]:
    """Rows written by :func:`write_rows_csv`, with numbers parsed back (empty cells are None)."""
    rows = []
    with Path(path).open(newline="") as handle:
        for raw in csv.DictReader(handle):
            row: dict = dict(raw)
            for key in ("seed", "step"):
                row[key] = int(row[key])
            for key in ("elapsed_s", "train_s", "train_cpu_s", "psnr", "ssim", "lpips", "lpips_vgg"):
                row[key] = float(row[key]) if row.get(key) not in ("", None) else None
            row["num_images"] = int(row["num_images"]) if row.get("num_images") not in ("", None) else None
            row["lpips_net"] = row.get("lpips_net") or None
            row["cpu"] = row.get("cpu") or ""
            rows.append(row)
    return rows


@dataclass
class Curve:
    """One method's metric against time on one scene, aggregated over seeds at each evaluated step.

    Arrays are [T] over the steps evaluated by every seed; ``time`` is the mean over seeds of the time key.
    """

    scene: str
    method: str
    metric: str
    steps: np.ndarray
    time: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    low: np.ndarray
    high: np.ndarray
    num_seeds: int
    seeds: list[int] = field(default_factory=list)


def aggregate_curves(rows: Sequence[dict], metric: str, time_key: str = DEFAULT_TIME_KEY) -> list[Curve]:
    """Per (scene, method): the metric's mean, std and min/max over seeds at each step that every seed evaluated.

    Steps missing from some seed are left out (a mean over a changing set of seeds would jump); rows whose metric is
    None (e.g. LPIPS unavailable) are ignored, and a (scene, method) with no value at all gives no curve.
    """
    if time_key not in TIME_KEYS:
        raise ValueError(f"time_key must be one of {sorted(TIME_KEYS)}, got '{time_key}'")
    groups: dict[tuple[str, str], dict[int, dict[int, dict]]] = {}
    for row in rows:
        if row.get(metric) is None:
            continue
        groups.setdefault((row["scene"], row["method"]), {}).setdefault(row["seed"], {})[row["step"]] = row
    curves = []
    for (scene, method), by_seed in groups.items():
        seeds = sorted(by_seed)
        common = sorted(set.intersection(*(
            {step for step, row in steps.items() if row.get(time_key) is not None} for steps in by_seed.values()
        )))
        if not common:
            continue
        values = np.array([[by_seed[s][step][metric] for step in common] for s in seeds], dtype=np.float64)
        times = np.array([[by_seed[s][step][time_key] for step in common] for s in seeds], dtype=np.float64)
        curves.append(
            Curve(
                scene=scene, method=method, metric=metric, steps=np.array(common), time=times.mean(0),
                mean=values.mean(0), std=values.std(0), low=values.min(0), high=values.max(0),
                num_seeds=len(seeds), seeds=seeds,
            )
        )
    return curves


def _ordered_methods(rows: Sequence[dict], baseline: str | None = None) -> list[str]:
    methods = list(dict.fromkeys(row["method"] for row in rows))
    if baseline in methods:
        methods.remove(baseline)
        methods.insert(0, baseline)
    return methods


def plot_metric_vs_time(
    rows: Sequence[dict], metric: str, path: str | Path, time_key: str = DEFAULT_TIME_KEY, baseline: str | None = None
) -> list[Curve]:
    """PNG of ``metric`` against seconds: one panel per scene, one curve per method (mean over seeds, min-max band).

    Returns the curves drawn (empty, and no file written, when no run has a value for the metric).
    """
    plt = pyplot()

    curves = aggregate_curves(rows, metric, time_key)
    if not curves:
        return []
    scenes = list(dict.fromkeys(c.scene for c in curves))
    methods = _ordered_methods(rows, baseline)
    colors = {m: plt.get_cmap("tab10")(i % 10) for i, m in enumerate(methods)}
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.5 * len(scenes), 4.0), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        for method in methods:
            for curve in (c for c in curves if c.scene == scene and c.method == method):
                label = f"{method} (n={curve.num_seeds})"
                ax.plot(curve.time, curve.mean, "-o", ms=3, color=colors[method], label=label)
                if curve.num_seeds > 1:
                    ax.fill_between(curve.time, curve.low, curve.high, color=colors[method], alpha=0.2, lw=0)
        positive = [c.time[c.time > 0] for c in curves if c.scene == scene]
        if any(p.size for p in positive) and max(float(p.max()) for p in positive if p.size) / max(
            min(float(p.min()) for p in positive if p.size), 1e-9
        ) > 20:
            ax.set_xscale("log")
        ax.set_xlabel(TIME_KEYS[time_key])
        label = metric_label(metric, rows)
        ax.set_ylabel(label)
        ax.set_title(f"{scene}: {label} vs time (mean, min-max over seeds)", fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    path = save_figure(fig, path, dpi=120)
    return curves


def lpips_networks(rows: Sequence[dict]) -> list[str]:
    """The LPIPS backbones the rows' values were measured with (normally one, 'alex')."""
    return sorted({row["lpips_net"] for row in rows if row.get("lpips") is not None and row.get("lpips_net")})


def metric_label(metric: str, rows: Sequence[dict] = ()) -> str:
    """Axis/table label; LPIPS names its network (``LPIPS (alex)``)."""
    label = METRIC_LABELS.get(metric, metric)
    if metric == "lpips" and lpips_networks(rows):
        label = f"{label} ({', '.join(lpips_networks(rows))})"
    return label


def final_rows(rows: Sequence[dict]) -> list[dict]:
    """Per (scene, method, seed), the evaluation at that run's last evaluated step."""
    last: dict[tuple, dict] = {}
    for row in rows:
        key = (row["scene"], row["method"], row["seed"])
        if key not in last or row["step"] > last[key]["step"]:
            last[key] = row
    return list(last.values())


def summarize_final(rows: Sequence[dict], baseline: str | None = None) -> list[dict]:
    """Per (scene, method): mean and std over seeds of the final metrics and training time, with deltas vs baseline.

    Deltas (present when the baseline ran on the scene): ``psnr_delta_db`` (difference of means), ``ssim_delta_pct``
    and ``lpips_delta_pct`` (relative change of the means, %), ``time_ratio`` (mean train_s / baseline's).
    """
    finals = final_rows(rows)
    scenes = list(dict.fromkeys(row["scene"] for row in finals))
    methods = _ordered_methods(finals, baseline)
    summary = []
    for scene in scenes:
        by_method = {}
        for method in methods:
            group = [r for r in finals if r["scene"] == scene and r["method"] == method]
            if not group:
                continue
            entry = {"scene": scene, "method": method, "num_seeds": len(group), "step": max(r["step"] for r in group)}
            for key in ("psnr", "ssim", "lpips", "train_s", "elapsed_s"):
                values = [r[key] for r in group if r.get(key) is not None]
                entry[key] = float(np.mean(values)) if values else None
                entry[f"{key}_std"] = float(np.std(values)) if values else None
            by_method[method] = entry
        base = by_method.get(baseline) if baseline else None
        for entry in by_method.values():
            if base is not None:
                entry["psnr_delta_db"] = _diff(entry["psnr"], base["psnr"])
                entry["ssim_delta_pct"] = _rel_pct(entry["ssim"], base["ssim"])
                entry["lpips_delta_pct"] = _rel_pct(entry["lpips"], base["lpips"])
                entry["time_ratio"] = (entry["train_s"] / base["train_s"]) if entry["train_s"] and base["train_s"] else None
            summary.append(entry)
    return summary


def _diff(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a - b


def _rel_pct(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None or b == 0 else 100.0 * (a - b) / abs(b)


def paired_difference(metric: str, value: float | None, base: float | None) -> float | None:
    """A method's ``value`` of ``metric`` minus the baseline's ``base`` at the same scene and seed: PSNR in dB, every
    other metric relative to the baseline (%); None when either is missing."""
    return (_diff if metric == "psnr" else _rel_pct)(value, base)


def _fmt(value: float | None, std: float | None, digits: int) -> str:
    if value is None:
        return "n/a"
    if std is None:
        return f"{value:.{digits}f}"
    return f"{value:.{digits}f} ± {std:.{digits}f}"


def format_mean_interval(value: float | None, interval: Sequence[float] | None = None, digits: int = 2) -> str:
    """``+m.mm [+lo, +hi]``: a signed mean with its interval when there is one; "n/a" for a missing mean."""
    if value is None:
        return "n/a"
    ci = f" [{interval[0]:+.{digits}f}, {interval[1]:+.{digits}f}]" if interval else ""
    return f"{value:+.{digits}f}{ci}"


def _signed(value: float | None, digits: int, unit: str) -> str:
    return "" if value is None else f" ({value:+.{digits}f}{unit})"


def markdown_table(
    summary: Sequence[dict], baseline: str | None = None, lpips_note: str | None = None, lpips_label: str = "LPIPS"
) -> str:
    """Markdown table of the final metrics (mean ± std over seeds), deltas vs ``baseline`` in parentheses."""
    lines = [
        f"| scene | method | seeds | step | PSNR (dB) ↑ | SSIM ↑ | {lpips_label} ↓ | train time (s) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in summary:
        is_base = e["method"] == baseline
        psnr = _fmt(e["psnr"], e["psnr_std"], 2) + ("" if is_base else _signed(e.get("psnr_delta_db"), 2, " dB"))
        ssim = _fmt(e["ssim"], e["ssim_std"], 4) + ("" if is_base else _signed(e.get("ssim_delta_pct"), 2, " %"))
        lpips = _fmt(e["lpips"], e["lpips_std"], 4) + ("" if is_base else _signed(e.get("lpips_delta_pct"), 2, " %"))
        time = _fmt(e["train_s"], e["train_s_std"], 1)
        if not is_base and e.get("time_ratio") is not None:
            time += f" ({e['time_ratio']:.2f}x)"
        name = f"{e['method']} (baseline)" if is_base else e["method"]
        lines.append(f"| {e['scene']} | {name} | {e['num_seeds']} | {e['step']} | {psnr} | {ssim} | {lpips} | {time} |")
    notes = ["", "Mean ± std over seeds of the last evaluation on the test split."]
    if baseline:
        notes.append(
            f"In parentheses: difference to `{baseline}` (PSNR in dB; SSIM and LPIPS relative, in %; time as a ratio)."
        )
    if lpips_note:
        notes.append(f"LPIPS: {lpips_note}")
    return "\n".join(lines + notes) + "\n"


def mean_interval(values: Sequence[float], level: float = INTERVAL_LEVEL) -> tuple[float, float] | None:
    """Student-t interval on the mean of ``values`` (paired differences over seeds): mean -/+ t_{(1+level)/2, n-1}
    s / sqrt(n), s the sample std (ddof 1). None for fewer than two values."""
    from scipy.stats import t as student_t

    array = np.asarray([v for v in values if v is not None], dtype=np.float64)
    if array.size < 2:
        return None
    half = float(student_t.ppf((1 + level) / 2, array.size - 1) * array.std(ddof=1) / np.sqrt(array.size))
    return float(array.mean() - half), float(array.mean() + half)


def paired_deltas(rows: Sequence[dict], baseline: str) -> list[dict]:
    """Per (scene, method), the final-metric differences to ``baseline`` run with the same seed.

    Runs that share a seed share the initial Gaussians and the image order, so pairing removes the seed-to-seed
    variation that dominates short runs. Returns ``seeds``, ``psnr_db`` (per-seed differences, dB), ``ssim_pct``,
    ``lpips_pct`` and ``lpips_vgg_pct`` (relative, %; None where unavailable), with their ``_mean`` and
    ``_interval`` (95 % Student t interval of the mean over seeds, None with fewer than two seeds:
    :func:`mean_interval`), and ``mixed_cpu_seeds``: the seeds whose two runs trained on different kinds of CPU
    (both recorded), whose difference then also holds a change of float32 rounding (kept: it acts like another
    seed, but the report names them).
    """
    finals = {(r["scene"], r["method"], r["seed"]): r for r in final_rows(rows)}
    out = []
    for scene, method in dict.fromkeys((k[0], k[1]) for k in finals):
        if method == baseline:
            continue
        seeds = sorted(k[2] for k in finals if k[:2] == (scene, method) and (scene, baseline, k[2]) in finals)
        if not seeds:
            continue
        entry: dict = {"scene": scene, "method": method, "seeds": seeds, "mixed_cpu_seeds": [
            s for s in seeds if _cpus_differ(finals[(scene, method, s)], finals[(scene, baseline, s)])]}
        for metric, key in PAIRED_METRICS.items():
            values = [paired_difference(metric, finals[(scene, method, s)].get(metric),
                                        finals[(scene, baseline, s)].get(metric)) for s in seeds]
            entry[key] = values
            present = [v for v in values if v is not None]
            entry[f"{key}_mean"] = float(np.mean(present)) if present else None
            entry[f"{key}_interval"] = mean_interval(present)
        out.append(entry)
    return out


def _cpus_differ(a: dict, b: dict) -> bool:
    return bool(a.get("cpu")) and bool(b.get("cpu")) and a["cpu"] != b["cpu"]


def pooled_deltas(paired: Sequence[dict]) -> list[dict]:
    """Per method, two estimates pooled over the scenes of :func:`paired_deltas`' entries:

    - ``all_pairs``: the mean of every (scene, seed) paired difference, with the t interval over all pairs (ddof 1,
      n - 1 degrees of freedom). It weights scenes by their number of pairs and treats pairs as independent draws.
    - ``per_scene``: the mean of the per-scene mean differences (each scene weighted equally: the average effect
      over these scenes), its standard error ``sqrt(sum_k s_k^2 / n_k) / K`` from the within-scene sample variances,
      and a t interval with Welch-Satterthwaite degrees of freedom. It does not generalise to other scenes: the
      between-scene spread is reported as ``scene_means`` beside it. With no within-scene variation at all (every
      scene's differences constant, e.g. a metric both methods hold fixed) the standard error is 0 and the interval
      is the point itself, as :func:`mean_interval` gives for constant values (the degrees of freedom, 0/0, are
      not needed then).
    """
    from scipy.stats import t as student_t

    out = []
    for method in dict.fromkeys(e["method"] for e in paired):
        entries = [e for e in paired if e["method"] == method]
        result: dict = {"method": method, "scenes": [e["scene"] for e in entries],
                        "num_pairs": sum(len(e["seeds"]) for e in entries)}
        for key in PAIRED_METRICS.values():
            per_scene = [np.asarray([v for v in e.get(key) or () if v is not None], dtype=np.float64) for e in entries]
            per_scene = [v for v in per_scene if v.size]
            if not per_scene:
                continue
            everything = np.concatenate(per_scene)
            result[f"{key}_all_pairs"] = float(everything.mean())
            result[f"{key}_all_pairs_interval"] = mean_interval(everything.tolist())
            means = np.array([v.mean() for v in per_scene])
            result[f"{key}_scene_means"] = means.tolist()
            result[f"{key}_per_scene"] = float(means.mean())
            if all(v.size >= 2 for v in per_scene):
                shares = np.array([v.var(ddof=1) / v.size for v in per_scene])
                se = float(np.sqrt(shares.sum()) / len(per_scene))
                if se > 0:
                    dof = float(shares.sum() ** 2 / np.sum(shares ** 2 / np.array([v.size - 1 for v in per_scene])))
                    half = float(student_t.ppf((1 + INTERVAL_LEVEL) / 2, dof) * se)
                else:
                    half = 0.0
                result[f"{key}_per_scene_interval"] = (float(means.mean()) - half, float(means.mean()) + half)
            else:
                result[f"{key}_per_scene_interval"] = None
        out.append(result)
    return out


def markdown_pooled_table(pooled: Sequence[dict], baseline: str) -> str:
    """Markdown of :func:`pooled_deltas`."""
    if not pooled:
        return ""

    def cell(entry: dict, key: str, kind: str, digits: int) -> str:
        return format_mean_interval(entry.get(f"{key}_{kind}"), entry.get(f"{key}_{kind}_interval"), digits)

    lines = [
        f"Pooled over scenes, differences to `{baseline}` at the same seed (final evaluation), "
        f"{100 * INTERVAL_LEVEL:.0f} % t intervals. *All pairs*: the mean over every (scene, seed) pair, t over "
        "pairs. *Per scene*: the mean of the per-scene means (scenes weighted equally), standard error from the "
        "within-scene variances, Welch-Satterthwaite degrees of freedom.",
        "",
        "| method | scenes | pairs | estimate | ΔPSNR (dB) | ΔSSIM (%) | ΔLPIPS alex (%) | ΔLPIPS VGG (%) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in pooled:
        for kind, name in (("all_pairs", "all pairs"), ("per_scene", "per scene")):
            lines.append(
                f"| {e['method']} | {len(e['scenes'])} | {e['num_pairs']} | {name} | {cell(e, 'psnr_db', kind, 2)} | "
                f"{cell(e, 'ssim_pct', kind, 2)} | {cell(e, 'lpips_pct', kind, 2)} | {cell(e, 'lpips_vgg_pct', kind, 2)} |"
            )
    return "\n".join(lines) + "\n"


def markdown_paired_table(paired: Sequence[dict], baseline: str) -> str:
    """Markdown of :func:`paired_deltas`: per-seed differences to the baseline and their mean."""
    if not paired:
        return ""

    def cells(values: list, mean: float | None, digits: int, interval: tuple[float, float] | None = None) -> str:
        if mean is None:
            return "n/a | n/a"
        per_seed = " / ".join("n/a" if v is None else f"{v:+.{digits}f}" for v in values)
        return f"{per_seed} | {format_mean_interval(mean, interval, digits)}"

    lines = [
        f"Per-seed differences to `{baseline}` at the same seed (final evaluation); mean with its "
        f"{100 * INTERVAL_LEVEL:.0f} % Student t interval over seeds in brackets:",
        "",
        "| scene | method | seeds | ΔPSNR per seed (dB) | mean [CI] | ΔSSIM per seed (%) | mean [CI] "
        "| ΔLPIPS alex per seed (%) | mean [CI] | ΔLPIPS VGG per seed (%) | mean [CI] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for e in paired:
        seeds = " / ".join(str(s) for s in e["seeds"])
        lines.append(
            f"| {e['scene']} | {e['method']} | {seeds} | "
            f"{cells(e['psnr_db'], e['psnr_db_mean'], 2, e.get('psnr_db_interval'))} | "
            f"{cells(e['ssim_pct'], e['ssim_pct_mean'], 2, e.get('ssim_pct_interval'))} | "
            f"{cells(e['lpips_pct'], e['lpips_pct_mean'], 2, e.get('lpips_pct_interval'))} | "
            f"{cells(e.get('lpips_vgg_pct', []), e.get('lpips_vgg_pct_mean'), 2, e.get('lpips_vgg_pct_interval'))} |"
        )
    mixed = [f"{e['scene']} {e['method']} seed {s}" for e in paired for s in e.get("mixed_cpu_seeds", [])]
    if mixed:
        lines += ["", f"Pairs whose two runs trained on different kinds of CPU (their difference also holds a change "
                      f"of float32 rounding): {', '.join(mixed)}."]
    return "\n".join(lines) + "\n"


def write_report(
    rows: Sequence[dict],
    out_dir: str | Path,
    baseline: str | None = None,
    time_key: str = DEFAULT_TIME_KEY,
    lpips_note: str | None = None,
    also_against: Sequence[str] = (),
) -> dict[str, Path]:
    """Everything :mod:`report` makes, under ``out_dir``: ``evals.csv``, ``evals.json``, ``summary.json``,
    ``results.md`` and one ``<metric>_vs_time.png`` per metric that has values. Returns the paths by name.

    ``also_against``: further reference methods; for each, ``results.md`` adds the per-seed (and, over several scenes,
    pooled) differences of every method but ``baseline`` and itself to it, and ``pooled.json`` holds them under
    ``also_against`` (for a three-arm study: the third arm against the second, not only against the baseline)."""
    if not rows:
        raise ValueError("write_report: no evaluation rows (did the runs evaluate? set eval_at_steps)")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"csv": write_rows_csv(rows, out_dir / "evals.csv")}
    paths["json"] = out_dir / "evals.json"
    paths["json"].write_text(json.dumps(list(rows), indent=1))
    summary = summarize_final(rows, baseline)
    paths["summary"] = out_dir / "summary.json"
    paths["summary"].write_text(json.dumps(summary, indent=1))
    paths["table"] = out_dir / "results.md"
    table = markdown_table(summary, baseline, lpips_note, lpips_label=metric_label("lpips", rows))
    comparisons = {}
    for reference in dict.fromkeys([baseline, *also_against] if baseline else also_against):
        others = rows if reference == baseline else [r for r in rows if r["method"] != baseline]
        paired = paired_deltas(others, reference)
        table += ("\n" + markdown_paired_table(paired, reference)) if paired else ""
        if len({e["scene"] for e in paired}) > 1:
            pooled = pooled_deltas(paired)
            table += "\n" + markdown_pooled_table(pooled, reference)
            comparisons[reference] = {"paired": paired, "pooled": pooled}
    if baseline in comparisons:
        also = {reference: found for reference, found in comparisons.items() if reference != baseline}
        paths["pooled"] = out_dir / "pooled.json"
        paths["pooled"].write_text(json.dumps({**comparisons[baseline], **({"also_against": also} if also else {})},
                                              indent=1))
    paths["table"].write_text(table)
    for metric in METRICS:
        png = out_dir / f"{metric}_vs_time.png"
        if plot_metric_vs_time(rows, metric, png, time_key, baseline):
            paths[f"plot_{metric}"] = png
    return paths


def gradient_share_series(records: Iterable[dict]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """From one run's ``metrics.jsonl`` records: per loss term, (steps [T], share of the photometric term [T])."""
    series: dict[str, tuple[list, list]] = {}
    for record in records:
        if record.get("kind") != "gradient_shares":
            continue
        for term, share in (record.get("share") or {}).items():
            steps, values = series.setdefault(term, ([], []))
            steps.append(int(record["step"]))
            values.append(np.nan if share is None else float(share))
    return {term: (np.array(steps), np.array(values)) for term, (steps, values) in series.items()}


def plot_gradient_shares(records_by_label: dict[str, Sequence[dict]], path: str | Path, title: str = "") -> Path | None:
    """PNG of each loss term's image-gradient norm relative to the photometric term's, against step (log y), one
    panel per run label (e.g. method). Returns None (no file) when no run logged ``gradient_shares`` records."""
    panels = {label: gradient_share_series(records) for label, records in records_by_label.items()}
    panels = {label: series for label, series in panels.items() if any(t != "main_loss" for t in series)}
    if not panels:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.0), squeeze=False)
    for ax, (label, series) in zip(axes[0], panels.items()):
        for term, (steps, shares) in series.items():
            if term == "main_loss":
                continue
            positive = np.where(shares > 0, shares, np.nan)  # a zero share cannot be drawn on a log axis
            zeros = int((shares == 0).sum())
            ax.plot(steps, 100 * positive, "-o", ms=3, label=term + (f" (exactly 0 at {zeros} steps)" if zeros else ""))
        ax.axhline(100, color="black", lw=0.8, ls="--", label="main_loss (= 100 %)")
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_ylabel("||d term / d image|| / ||d main_loss / d image|| (%)")
        ax.set_title(f"{title + ': ' if title else ''}{label}", fontsize=9)
        ax.grid(True, alpha=0.3, which="both")
        ax.legend(fontsize=8)
    return save_figure(fig, path, dpi=120)
