"""Evaluation of a split: PSNR and SSIM per image and their means; LPIPS only where its weights exist offline.

SSIM convention: kornia's Gaussian-window SSIM (window 11, sigma 1.5, reflect 'same' padding), averaged over the image, as
``kc_splatfacto.metrics.mean_ssim`` computes it (nerfstudio's torchmetrics SSIM uses 'valid' windows instead; the
two differ slightly near borders). The model compares each view (``SplatfactoModel.get_image_metrics``): RGBA ground
truth composited over the render's background, and PSNR / SSIM over the view's mask when it has one.
"""

from __future__ import annotations

import math
import time
from typing import Any

import torch

SSIM_CONVENTION = "kornia ssim, gaussian window 11, sigma 1.5, reflect same padding, image mean"


def lpips_metric() -> tuple[Any | None, str | None]:
    """An LPIPS(alex) callable on [B, 3, H, W] images in [0, 1], or (None, the reason it is unavailable).

    LPIPS needs pretrained network weights; they are never downloaded here (runs must work offline), so it is only
    available where the ``lpips`` package and its torchvision backbone weights are already installed and cached.
    """
    try:
        import lpips  # noqa: F401  (optional; needs torchvision and cached AlexNet weights)
    except Exception as exc:  # ImportError, or torchvision missing inside it
        return None, f"LPIPS needs the 'lpips' package with torchvision and its pretrained weights offline ({exc})"
    try:
        net = lpips.LPIPS(net="alex", verbose=False)
    except Exception as exc:
        return None, f"LPIPS weights could not be loaded offline ({exc})"
    net.eval()

    def compute(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        return net.to(pred.device)(pred * 2 - 1, gt * 2 - 1).mean()

    return compute, None


def _image_name(dataset, index: int) -> str | None:
    outputs = getattr(dataset, "outputs", None)
    names = getattr(outputs, "image_filenames", None) or getattr(dataset, "image_filenames", None)
    return str(names[index]) if names is not None else None


def _mean_std(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / len(values))
    return mean, std


@torch.no_grad()
def evaluate_split(model, dataset, *, with_lpips: bool = True) -> dict[str, Any]:
    """Render every image of ``dataset`` with ``model`` (in eval mode) and compare with the ground truth.

    Returns:
        ``psnr``, ``ssim`` (means), ``psnr_std``, ``ssim_std``, ``lpips`` (mean or None), ``lpips_unavailable``
        (the reason, when None), ``num_images``, ``render_fps``, ``ssim_convention`` and ``per_image``: a list of
        ``{"index", "image", "psnr", "ssim", "lpips"}``.
    """
    if len(dataset) == 0:
        raise ValueError("evaluate_split: the dataset is empty (no images in this split)")
    lpips_fn, lpips_reason = lpips_metric() if with_lpips else (None, "not requested")
    was_training = model.training
    model.eval()
    per_image: list[dict[str, Any]] = []
    render_time = 0.0
    try:
        for index in range(len(dataset)):
            camera = dataset.cameras[index]
            t0 = time.perf_counter()
            outputs = model.get_outputs(camera)
            render_time += time.perf_counter() - t0
            try:
                metrics, (pred, gt) = model.get_image_metrics(outputs, dataset[index])
            except ValueError as exc:
                raise ValueError(f"image {index} ({_image_name(dataset, index)}): {exc}") from exc
            record = {
                "index": index,
                "image": _image_name(dataset, index),
                "psnr": metrics["psnr"],
                "ssim": metrics["ssim"],
                "lpips": float(lpips_fn(pred, gt)) if lpips_fn is not None else None,
            }
            per_image.append(record)
    finally:
        model.train(was_training)
    psnr_mean, psnr_std = _mean_std([r["psnr"] for r in per_image])
    ssim_mean, ssim_std = _mean_std([r["ssim"] for r in per_image])
    lpips_mean, lpips_std = _mean_std([r["lpips"] for r in per_image]) if lpips_fn is not None else (None, None)
    result: dict[str, Any] = {
        "psnr": psnr_mean,
        "psnr_std": psnr_std,
        "ssim": ssim_mean,
        "ssim_std": ssim_std,
        "lpips": lpips_mean,
        "lpips_std": lpips_std,
        "num_images": len(per_image),
        "render_fps": len(per_image) / render_time if render_time > 0 else None,
        "ssim_convention": SSIM_CONVENTION,
        "per_image": per_image,
    }
    if lpips_fn is None:
        result["lpips_unavailable"] = lpips_reason
    return result
