"""Side-by-side test views of finished runs: one row per view, one column per run, the ground truth last.

    python benchmarks/test_views_figure.py --out docs/results/castle-P30-7k/test_views_7k_seed0.png \\
        splatfacto=outputs/study-castle-P30-7k/castle-P30/splatfacto/seed0 \\
        kc-splatfacto=outputs/study-castle-P30-7k/castle-P30/kc-splatfacto/seed0 --views 0 3 9

Each run is loaded from its newest checkpoint (``--step`` picks another) the way ``kc-eval`` loads it, each view is
rendered and titled with its PSNR against the ground truth as evaluated (RGBA composited on the model's
background). Prints the per-view PSNR table. Runs must be of the same scene (same test split).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_DIR, one per column")
    parser.add_argument("--views", nargs="+", type=int, required=True, help="test view indices, one per row")
    parser.add_argument("--step", type=int, default=None, help="checkpoint step (default: each run's newest)")
    parser.add_argument("--out", required=True, type=Path, help="PNG to write")
    args = parser.parse_args(argv)

    from kc_splatfacto.analysis.figures import pyplot, save_figure
    from kc_splatfacto.cli.eval import render_view
    from kc_splatfacto.engine.run_io import load_run
    from kc_splatfacto.metrics import psnr
    from kc_splatfacto.losses.layout import composite_with_background
    from sweep_report import labelled_run_dir  # benchmarks/ is on sys.path when this runs as a script

    columns: dict[str, tuple[int, list[np.ndarray], list[float]]] = {}  # label -> (step, renders, PSNRs) per view
    truth: list[np.ndarray] = []
    for spec in args.runs:
        label, folder = labelled_run_dir(spec, required=("config.yml",))
        loaded = load_run(folder / "config.yml", step=args.step, device="cpu")
        dataset = loaded.test_dataset
        bad = [v for v in args.views if not 0 <= v < len(dataset)]
        if bad:
            raise SystemExit(f"test_views_figure: views {bad} are outside the {len(dataset)} test views of {folder}")
        images: list[np.ndarray] = []
        scores: list[float] = []
        columns[label] = (loaded.step, images, scores)
        for k, view in enumerate(args.views):
            rgb, _ = render_view(loaded.model, dataset.cameras, view)
            gt = composite_with_background(dataset.image_float(view), loaded.model.background_color)
            scores.append(float(psnr(rgb.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None])))
            images.append(rgb.numpy())
            if len(truth) <= k:
                truth.append(gt.numpy())
            elif truth[k].shape != gt.shape or not np.allclose(truth[k], gt.numpy()):
                raise SystemExit(f"test_views_figure: {folder} has another test view {view} than the first run")

    plt = pyplot()
    height, width = truth[0].shape[:2]
    ncols = len(columns) + 1
    fig, axes = plt.subplots(len(args.views), ncols, figsize=(2.6 * ncols, 2.6 * height / width * len(args.views) + 0.4),
                             squeeze=False)
    for row, view in enumerate(args.views):
        for col, (label, (step, images, scores)) in enumerate(columns.items()):
            axes[row][col].imshow(np.clip(images[row], 0, 1))
            axes[row][col].set_title(f"{label} (step {step})\nview {view}: {scores[row]:.2f} dB", fontsize=7)
        axes[row][-1].imshow(np.clip(truth[row], 0, 1))
        axes[row][-1].set_title(f"ground truth, view {view}", fontsize=7)
        for ax in axes[row]:
            ax.axis("off")
    fig.tight_layout()
    save_figure(fig, args.out, dpi=130)
    print("| view | " + " | ".join(columns) + " |")
    print("|---" * (len(columns) + 1) + "|")
    for row, view in enumerate(args.views):
        print(f"| {view} | " + " | ".join(f"{scores[row]:.2f}" for _, _, scores in columns.values()) + " |")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
