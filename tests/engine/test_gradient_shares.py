"""Gradient shares: analytic L1/MSE norms, finite differences through the real KC-3DGS terms, the pixel
concentration against numpy, the trainer's records (and that logging them leaves training unchanged), the plot."""

import math

import cv2
import numpy as np
import pytest
import torch

from kc_splatfacto.engine.gradient_shares import gradient_shares, top_pixel_fraction
from kc_splatfacto.engine.metrics_log import read_metrics
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.losses.frequency import FrequencyLoss
from tests.training_utils import tiny_demo_config


def test_l1_and_mse_norms_match_their_closed_forms():
    torch.manual_seed(0)
    gt = torch.rand(12, 10, 3, dtype=torch.float64)
    diff = torch.rand_like(gt) * 0.5 + 0.1  # no zero difference: d|x|/dx = sign(x) everywhere
    sign = torch.where(torch.rand_like(gt) > 0.5, 1.0, -1.0)
    image = (gt + sign * diff).requires_grad_()
    n = gt.numel()
    w_l1, w_mse = 0.8, 3.0
    losses = {"main_loss": w_l1 * (image - gt).abs().mean(), "mse": w_mse * ((image - gt) ** 2).mean()}
    out = gradient_shares(losses, image)
    l1_norm = w_l1 / math.sqrt(n)  # |d/dx_i| = w / n for each of n elements
    mse_norm = 2 * w_mse * float(torch.linalg.vector_norm(diff)) / n
    assert out["norm"]["main_loss"] == pytest.approx(l1_norm, rel=1e-12)
    assert out["norm"]["mse"] == pytest.approx(mse_norm, rel=1e-12)
    assert out["share"]["main_loss"] == 1.0
    assert out["share"]["mse"] == pytest.approx(mse_norm / l1_norm, rel=1e-12)
    assert out["top"]["main_loss"] == pytest.approx(math.ceil(0.01 * 120) / 120)  # uniform: k pixels of 120
    # the graph is retained: the caller's backward still works
    sum(losses.values()).backward()
    assert image.grad is not None


def test_top_pixel_fraction_matches_numpy():
    rng = np.random.default_rng(1)
    grad = rng.standard_normal((20, 30, 3)) * np.exp(3 * rng.standard_normal((20, 30, 1)))
    energy = (grad**2).sum(-1).ravel()
    k = 6  # ceil(1 % of 600)
    expected = np.sort(energy)[::-1][:k].sum() / energy.sum()
    assert top_pixel_fraction(torch.from_numpy(grad)) == pytest.approx(expected, rel=1e-12)
    assert top_pixel_fraction(torch.from_numpy(grad), 1.0) == pytest.approx(1.0)
    assert math.isnan(top_pixel_fraction(torch.zeros(4, 4, 3)))


def _finite_difference_directional(fn, image, direction, eps=1e-6):
    with torch.no_grad():
        return (float(fn(image + eps * direction)) - float(fn(image - eps * direction))) / (2 * eps)


@pytest.mark.parametrize("term", ["wavelet_loss", "kc_loss", "cbc_loss"])
def test_norms_of_the_kc3dgs_terms_agree_with_finite_differences(term):
    # in float64 on a 48x48 render: the derivative along the reported gradient's direction must equal its norm, and
    # along a random direction the gradient's projection (both from central differences)
    torch.manual_seed(3)
    gt = torch.rand(1, 3, 48, 48, dtype=torch.float64)
    pred = (gt + 0.1 * torch.randn_like(gt)).clamp(0, 1)
    loss = FrequencyLoss(wavelet_weight=1e-3, kc_weight=1e-5, cbc_weight=1e-2)
    target = loss.prepare_target(gt)
    image = pred.permute(0, 2, 3, 1)[0].clone().requires_grad_()  # [H, W, 3], the model's render layout

    def terms(img):
        bchw = img.permute(2, 0, 1)[None]
        return {"main_loss": (bchw - gt).abs().mean(), **loss(bchw, target)}

    out = gradient_shares(terms(image), image)
    (grad,) = torch.autograd.grad(terms(image)[term], image)
    norm = out["norm"][term]
    assert norm == pytest.approx(float(torch.linalg.vector_norm(grad)), rel=1e-12)
    along = _finite_difference_directional(lambda x: terms(x)[term], image.detach(), grad / norm)
    assert along == pytest.approx(norm, rel=1e-4)
    random_dir = torch.randn_like(grad)
    random_dir /= torch.linalg.vector_norm(random_dir)
    projected = _finite_difference_directional(lambda x: terms(x)[term], image.detach(), random_dir)
    assert projected == pytest.approx(float((grad * random_dir).sum()), rel=1e-3, abs=1e-9 * norm)
    assert out["share"][term] == pytest.approx(norm / out["norm"]["main_loss"], rel=1e-12)


def test_wrt_extra_tensors_and_unreachable_terms():
    torch.manual_seed(0)
    means = torch.randn(5, 3, requires_grad=True)
    image = (means.sum() * torch.ones(4, 4, 3)).sin()
    losses = {"main_loss": image.mean(), "other": (image**2).mean(), "scale_reg": (means**2).sum() * 0 + means.sum()}
    out = gradient_shares(losses, image, wrt={"means": means})
    assert "scale_reg" not in out["norm"]  # no path to the image
    assert set(out["norm_means"]) == {"main_loss", "other", "scale_reg"}
    (g,) = torch.autograd.grad(losses["other"], means, retain_graph=True)
    assert out["norm_means"]["other"] == pytest.approx(float(torch.linalg.vector_norm(g)), rel=1e-6)
    with pytest.raises(KeyError, match="reference term"):
        gradient_shares({"other": losses["other"]}, image)
    with pytest.raises(ValueError, match="does not require grad"):
        gradient_shares(losses, image.detach())


def test_trainer_logs_shares_without_changing_training(tmp_path):
    runs = {}
    for every in (0, 5):
        config = tiny_demo_config("kc-splatfacto", tmp_path / f"every{every}", iterations=20)
        config.logging.steps_per_gradient_shares = every
        trainer = Trainer(config)
        run_dir = trainer.train()
        runs[every] = (trainer, read_metrics(run_dir / "metrics.jsonl"))
    for name, param in runs[0][0].model.gauss_params.items():
        assert torch.equal(param, runs[5][0].model.gauss_params[name]), name
    assert not [r for r in runs[0][1] if r["kind"] == "gradient_shares"]
    records = [r for r in runs[5][1] if r["kind"] == "gradient_shares"]
    assert [r["step"] for r in records] == [5, 10, 15, 20]
    for record in records:
        assert set(record["share"]) == {"main_loss", "wavelet_loss", "kc_loss", "cbc_loss"}
        assert record["share"]["main_loss"] == 1.0 and record["reference"] == "main_loss"
        assert all(v >= 0 for v in record["share"].values()) and record["share"]["wavelet_loss"] > 0
        assert all(0 < v <= 1 for v in record["top"].values())


def test_gradient_share_plot(tmp_path):
    from kc_splatfacto.analysis.report import gradient_share_series, plot_gradient_shares

    records = [{"kind": "gradient_shares", "step": s, "share": {"main_loss": 1.0, "kc_loss": 0.1 * s, "cbc_loss": 0.0}}
               for s in (10, 20, 30)] + [{"kind": "train", "step": 10}]
    series = gradient_share_series(records)
    assert series["kc_loss"][0].tolist() == [10, 20, 30]
    assert np.allclose(series["kc_loss"][1], [1.0, 2.0, 3.0])
    path = plot_gradient_shares({"kc-splatfacto": records}, tmp_path / "shares.png", title="demo")
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    assert image is not None and image.std() > 0
    assert plot_gradient_shares({"splatfacto": [{"kind": "train", "step": 1}]}, tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()
