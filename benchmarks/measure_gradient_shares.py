"""Gradient shares of the KC-3DGS terms at the paper's weights on one castle-P30 training view (single renders).

For the view, with ``kc-splatfacto``'s loss (main_loss = 0.8 L1 + 0.2 (1 - SSIM), wavelet L1 1e-3, supervised KC
1e-5, supervised CBC 1e-2), prints each term's gradient norm relative to main_loss's, with respect to the image and
(for the render) to the means, and the fraction of the squared image gradient in the top 1 % of pixels, for:

- the render of the seed-point Gaussians (the state at step 0), or of a run's checkpoint with ``--load-config``;
- the ground truth blurred by a Gaussian of sigma 1, 2 and 4 pixels standing in for the render (a blurry render, the
  state the KC term is meant to fight).

    .venv/bin/python benchmarks/measure_gradient_shares.py [--data ../shared/data/castle-P30] [--view 0]
        [--load-config outputs/.../config.yml]
"""

from __future__ import annotations

import argparse
import copy
from pathlib import Path

import kc_splatfacto  # noqa: F401  (sets OMP_WAIT_POLICY before torch loads)
import torch  # noqa: E402
from kornia.filters import gaussian_blur2d  # noqa: E402

from kc_splatfacto.data.detect import AutoDataParserConfig  # noqa: E402
from kc_splatfacto.engine.gradient_shares import gradient_shares  # noqa: E402
from kc_splatfacto.registry import discover_methods  # noqa: E402

TERMS = ("wavelet_loss", "kc_loss", "cbc_loss")
BLUR_SIGMAS = (1.0, 2.0, 4.0)


def gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """[H, W, 3] -> the same blurred by a separable Gaussian (radius 3 sigma, reflect padding)."""
    size = 2 * int(round(3 * sigma)) + 1
    return gaussian_blur2d(image.permute(2, 0, 1)[None], (size, size), (sigma, sigma))[0].permute(1, 2, 0)


def build(args):
    if args.load_config:
        from kc_splatfacto.engine.run_io import load_run

        loaded = load_run(args.load_config)
        model, dataset, label = loaded.model, loaded.train_dataset, f"render at step {loaded.step}"
        # the paper's weights, whatever the run used
        paper = discover_methods()["kc-splatfacto"].config.pipeline.model
        for key in ("wavelet_weight", "kc_weight", "cbc_weight"):
            setattr(model.config, key, getattr(paper, key))
        model._frequency_loss = None
        return model, dataset, label
    config = copy.deepcopy(discover_methods()["kc-splatfacto"].config)
    config.pipeline.datamanager.dataparser = AutoDataParserConfig(data=Path(args.data),
                                                                  downscale_factor=args.downscale_factor)
    config.pipeline.model.num_downscales = 0
    datamanager = config.pipeline.datamanager.setup(seed=0)
    torch.manual_seed(0)
    model = config.pipeline.model.setup(
        scene_scale=float(datamanager.train_outputs.scene_scale),
        num_train_data=len(datamanager.train_dataset),
        seed_points=datamanager.seed_points(),
    )
    return model, datamanager.train_dataset, "render at step 0 (seed points)"


def row(label: str, out: dict) -> str:
    cells = []
    for term in TERMS:
        share = out["share"].get(term)
        top = out["top"].get(term)
        means = out.get("share_means", {}).get(term)
        cell = "n/a" if share is None else f"{100 * share:.3g} %"
        if means is not None:
            cell += f" (means {100 * means:.3g} %)"
        if top is not None:
            cell += f", top 1 %: {100 * top:.0f} %"
        cells.append(cell)
    return f"| {label} | " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[1].parent / "shared" / "data" / "castle-P30"))
    parser.add_argument("--downscale-factor", type=int, default=4)
    parser.add_argument("--view", type=int, default=0, help="training view index")
    parser.add_argument("--load-config", default=None, help="a run's config.yml: measure its latest checkpoint")
    args = parser.parse_args()
    model, dataset, label = build(args)
    model.train()
    model.set_step(10**6)  # full SH degree and resolution; density control is never called here
    camera, gt = dataset.cameras[args.view], dataset.image_float(args.view)
    batch = {"image": gt, "image_idx": None}

    outputs = model.get_outputs(camera)
    losses = model.get_loss_dict(outputs, batch)
    print(f"castle-P30 view {args.view}, {tuple(gt.shape[:2])}, {model.num_points} Gaussians, paper's weights")
    print("| image | " + " | ".join(TERMS) + " |")
    print("|---|---|---|---|")
    print(row(label, gradient_shares(losses, outputs["rgb"], wrt={"means": model.means})))
    for sigma in BLUR_SIGMAS:
        image = gaussian_blur(gt, sigma).clamp(0, 1).requires_grad_()
        losses = model.get_loss_dict({"rgb": image, "background": outputs["background"]}, batch)
        print(row(f"GT blurred, sigma {sigma:g} px", gradient_shares(losses, image)))


if __name__ == "__main__":
    main()
