"""``kc-eval --load-config outputs/.../config.yml [--output-path metrics.json]``: test-split metrics as ns-eval writes them.

JSON shape (ns-eval's, plus what a reader needs to trust the numbers)::

    {"experiment_name", "method_name", "checkpoint", "step",
     "results": {"psnr", "psnr_std", "ssim", "ssim_std", "lpips", "lpips_std", "lpips_net", "lpips_unavailable",
                 "num_rays_per_sec", "fps", "num_images"},
     "per_image": [{"index", "image", "psnr", "ssim", "lpips"}],
     "ssim_convention": "...", "psnr_convention": "..."}

PSNR and SSIM are computed per image on the float render against the float ground truth by the trainer's own
``evaluate_split``, then averaged (std over images, population). LPIPS is v0.1 with AlexNet (``lpips_net``; see
:mod:`kc_splatfacto.lpips`); where its weights are not installed it is null with the reason (and the install
command), never approximated.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.cli.main import ArgumentParser, add_run_arguments, check_output_path, existing_run_config, run_cli
from kc_splatfacto.engine.evaluation import evaluate_split
from kc_splatfacto.engine.run_io import load_run
from kc_splatfacto.errors import UserError

SSIM_CONVENTION = (
    "SSIM (not D-SSIM): kornia.metrics.ssim, gaussian window 11x11 sigma 1.5, C1=0.01^2, C2=0.03^2, reflect padding, "
    "mean over pixels and RGB channels of one image in [0,1]; the training loss uses 1 - SSIM"
)
PSNR_CONVENTION = "PSNR = -10 log10(MSE) over pixels and RGB channels of one image in [0,1], averaged over images"


def checkpoint_path(run_dir: Path, step: int) -> Path:
    """The checkpoint file of ``step`` in a run folder (nerfstudio's naming)."""
    return Path(run_dir) / "nerfstudio_models" / f"step-{step:09d}.ckpt"


def render_view(model, cameras, index: int):
    """[H,W,3] float render of camera ``index`` (no gradients), clamped to [0,1], and the seconds it took."""
    start = time.perf_counter()
    with torch.no_grad():
        outputs = model.get_outputs(cameras[index])
    rgb = outputs["rgb"].detach().clamp(0, 1)
    return rgb, time.perf_counter() - start


def evaluate_loaded_run(loaded, split: str = "test") -> dict:
    """ns-eval's ``results`` and the per-image values of ``loaded`` (a :class:`run_io.LoadedRun`) on one split.

    The numbers come from :func:`kc_splatfacto.engine.evaluation.evaluate_split`, the same function the trainer's
    evaluation records use, so kc-eval and ``metrics.jsonl`` agree.
    """
    dataset = loaded.test_dataset if split == "test" else loaded.train_dataset
    if dataset is None or len(dataset) == 0:
        raise UserError(f"kc-eval: the {split} split of {loaded.run_dir} has no images; nothing to evaluate")
    evaluation = evaluate_split(loaded.model, dataset)
    height, width = dataset.image_float(0).shape[:2]
    fps = evaluation.get("render_fps")
    results = {
        key: evaluation.get(key) for key in ("psnr", "psnr_std", "ssim", "ssim_std", "lpips", "lpips_std", "lpips_net")
    }
    if results["lpips"] is None:
        results["lpips_unavailable"] = evaluation.get("lpips_unavailable")
    results.update(
        {
            "fps": fps,
            "num_rays_per_sec": fps * height * width if fps is not None else None,
            "num_images": evaluation["num_images"],
        }
    )
    return {"results": results, "per_image": evaluation["per_image"], "ssim_convention": evaluation.get("ssim_convention")}


def run_eval(load_config: Path, output_path: Path | None = None, step: int | None = None, split: str = "test") -> dict:
    """Load a run, evaluate ``split``, write the JSON (when ``output_path``) and return it."""
    load_config = existing_run_config("kc-eval", load_config)
    loaded = load_run(load_config, step=step, device="cpu")
    evaluation = evaluate_loaded_run(loaded, split)
    config = loaded.config
    payload = {
        "experiment_name": getattr(config, "experiment_name", None),
        "method_name": getattr(config, "method_name", None),
        "checkpoint": str(checkpoint_path(loaded.run_dir, loaded.step)),
        "step": int(loaded.step),
        "split": split,
        "results": evaluation["results"],
        "per_image": evaluation["per_image"],
        "ssim_convention": f"{SSIM_CONVENTION} ({evaluation['ssim_convention']})"
        if evaluation.get("ssim_convention")
        else SSIM_CONVENTION,
        "psnr_convention": PSNR_CONVENTION,
    }
    if output_path is not None:
        atomic_write_text(output_path, json.dumps(payload, indent=2))
    return payload


def entrypoint(argv: list[str] | None = None) -> int:
    """``kc-eval``: user errors are one line and exit code 2 (``--debug`` shows the traceback)."""
    return run_cli("kc-eval", main, argv)


def main(argv: list[str]) -> int:
    parser = ArgumentParser(prog="kc-eval", description="Evaluate a trained run on its test split (ns-eval's JSON).")
    add_run_arguments(parser)
    parser.add_argument("--output-path", type=Path, default=Path("metrics.json"), help="where to write the JSON")
    parser.add_argument("--split", choices=("test", "train"), default="test")
    args = parser.parse_args(argv)
    check_output_path(args.output_path, "--output-path", parser.get_default("output_path"))
    payload = run_eval(args.load_config, args.output_path, args.step, args.split)
    r = payload["results"]
    lpips = "LPIPS n/a" if r["lpips"] is None else f"LPIPS({r['lpips_net']}) {r['lpips']:.4f}"
    print(
        f"{payload['method_name']} step {payload['step']}: PSNR {r['psnr']:.3f} ± {r['psnr_std']:.3f} dB, "
        f"SSIM {r['ssim']:.4f} ± {r['ssim_std']:.4f}, {lpips}, {r['fps']:.1f} fps over {r['num_images']} images "
        f"-> {args.output_path}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(entrypoint())
