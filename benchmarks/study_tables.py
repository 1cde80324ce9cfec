"""The tables a study's README shows, from the files ``kc-bench`` wrote (``pooled.json``, ``evals.csv``): per scene
(ΔPSNR per seed, means with their 95 % t intervals, pairs worse in LPIPS), pooled over the scenes, and the cost
(training CPU seconds at the last step relative to the baseline's, per pair).

    python benchmarks/study_tables.py docs/results/study-7k [--baseline splatfacto] [--step 7000]

The numbers are kc-bench's (``kc_splatfacto.analysis.report``); this only lays them out, so a README's tables can be
remade from the committed files.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Sequence

from kc_splatfacto.analysis.report import format_mean_interval


def _interval(mean: float | None, interval: Sequence[float] | None) -> str:
    """The report's ``mean [lo, hi]``, with a NaN mean (no pairs) shown as "n/a" too."""
    return format_mean_interval(None if mean is None or math.isnan(mean) else mean, interval)


def per_scene_table(paired: list[dict]) -> str:
    lines = ["| scene | arm | seeds | ΔPSNR (dB) per seed | ΔPSNR mean [95 % CI] | ΔSSIM (%) mean [CI] | "
             "ΔLPIPS-VGG (%) mean [CI], pairs worse | ΔLPIPS-alex (%) mean [CI], pairs worse |",
             "|---|---|---|---|---|---|---|---|"]
    for entry in paired:
        per_seed = " / ".join(f"{v:+.2f}" for v in entry["psnr_db"])

        def mean(key: str, entry: dict = entry) -> str:
            return _interval(entry.get(f"{key}_mean"), entry.get(f"{key}_interval"))
        worse = {key: f"{sum(v > 0 for v in entry[key])} of {len(entry[key])}" for key in ("lpips_vgg_pct", "lpips_pct")}
        lines.append(f"| {entry['scene']} | {entry['method']} | {len(entry['seeds'])} | {per_seed} | "
                     f"{mean('psnr_db')} | {mean('ssim_pct')} | {mean('lpips_vgg_pct')}, {worse['lpips_vgg_pct']} | "
                     f"{mean('lpips_pct')}, {worse['lpips_pct']} |")
    return "\n".join(lines)


def pooled_table(pooled: list[dict]) -> str:
    lines = ["| arm | estimate | ΔPSNR (dB) | ΔSSIM (%) | ΔLPIPS-VGG (%) | ΔLPIPS-alex (%) |", "|---|---|---|---|---|---|"]
    for entry in pooled:
        for estimate, label in (("all_pairs", "all pairs"), ("per_scene", "per scene")):
            cells = [_interval(entry.get(f"{key}_{estimate}"), entry.get(f"{key}_{estimate}_interval"))
                     for key in ("psnr_db", "ssim_pct", "lpips_vgg_pct", "lpips_pct")]
            lines.append(f"| {entry['method']} ({entry['num_pairs']} pairs) | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def cost_ratios(evals_csv: Path, baseline: str, step: int) -> dict[str, list[float]]:
    """Per arm, the ratios train_cpu_s(arm) / train_cpu_s(baseline) at ``step`` over the (scene, seed) pairs."""
    times: dict[tuple[str, int], dict[str, float]] = defaultdict(dict)
    with open(evals_csv, newline="") as handle:
        for row in csv.DictReader(handle):
            if int(row["step"]) == step and row["train_cpu_s"]:
                times[(row["scene"], int(row["seed"]))][row["method"]] = float(row["train_cpu_s"])
    ratios: dict[str, list[float]] = defaultdict(list)
    for by_method in times.values():
        if baseline not in by_method:
            continue
        for method, value in by_method.items():
            if method != baseline:
                ratios[method].append(value / by_method[baseline])
    return dict(ratios)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("study_dir", type=Path)
    parser.add_argument("--baseline", default="splatfacto")
    parser.add_argument("--step", type=int, default=7000)
    args = parser.parse_args()
    report = json.loads((args.study_dir / "pooled.json").read_text())
    print(per_scene_table(report["paired"]), end="\n\n")
    print(pooled_table(report["pooled"]), end="\n\n")
    for reference, against in report.get("also_against", {}).items():  # kc-bench --also-against
        print(f"against {reference}:", end="\n\n")
        print(per_scene_table(against["paired"]), end="\n\n")
        print(pooled_table(against["pooled"]), end="\n\n")
    for method, ratios in cost_ratios(args.study_dir / "evals.csv", args.baseline, args.step).items():
        print(f"cost {method}: {sum(ratios) / len(ratios):.3f}x {args.baseline}'s training CPU time at step "
              f"{args.step} ({min(ratios):.2f}-{max(ratios):.2f} over {len(ratios)} pairs)")


if __name__ == "__main__":
    main()
