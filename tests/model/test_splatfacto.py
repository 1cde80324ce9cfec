"""The model: outputs contract, loss-dict keys by weight, the Splatfacto loss formula, metrics."""

import itertools

import numpy as np
import pytest
import torch

from kc_splatfacto.data import ImageDataset
from kc_splatfacto.data.demo import DemoDataParserConfig
from kc_splatfacto.losses.frequency import FrequencyLossConfig
from kc_splatfacto.model.splatfacto import EVAL_BACKGROUND, SplatfactoModelConfig


@pytest.fixture(scope="module")
def demo_train():
    parser = DemoDataParserConfig(width=64, height=48).setup()
    outputs = parser.get_dataparser_outputs("train")
    return outputs, ImageDataset(outputs)


def make_model(demo_train, **overrides):
    outputs, dataset = demo_train
    config = SplatfactoModelConfig(num_downscales=0, **overrides)
    torch.manual_seed(0)
    model = config.setup(scene_scale=outputs.scene_scale, num_train_data=len(dataset),
                         seed_points=(outputs.points3d_xyz, outputs.points3d_rgb))
    return model, dataset


def test_outputs_contract(demo_train):
    model, dataset = make_model(demo_train)
    model.train()
    out = model.get_outputs(dataset.cameras[0])
    assert out["rgb"].shape == (48, 64, 3) and out["accumulation"].shape == (48, 64, 1)
    assert out["depth"] is None  # no depth while training (Splatfacto's default)
    assert 0 <= out["rgb"].min() and out["rgb"].max() <= 1
    assert out["background"].shape == (3,)
    background_a = out["background"]
    background_b = model.get_outputs(dataset.cameras[0])["background"]
    assert not torch.equal(background_a, background_b)  # random background in training
    model.eval()
    with torch.no_grad():
        out = model.get_outputs(dataset.cameras[0])
    assert out["depth"].shape == (48, 64, 1)
    assert torch.allclose(out["background"], torch.tensor(EVAL_BACKGROUND))
    # empty pixels show the background: rgb = render + (1 - alpha) * background
    empty = out["accumulation"][..., 0] < 1e-6
    if empty.any():
        assert torch.allclose(out["rgb"][empty], torch.tensor(EVAL_BACKGROUND).expand(int(empty.sum()), 3))


@pytest.mark.parametrize("weights", list(itertools.product([0.0, 1e-3], [0.0, 1e-5], [0.0, 1e-2])))
def test_loss_terms_present_only_when_weighted(demo_train, weights):
    wavelet, kc, cbc = weights
    model, dataset = make_model(demo_train, frequency=FrequencyLossConfig(wavelet_weight=wavelet, kc_weight=kc, cbc_weight=cbc))
    model.train()
    out = model.get_outputs(dataset.cameras[0])
    losses = model.get_loss_dict(out, {"image": dataset.image_uint8(0), "image_idx": 0})
    expected = {"main_loss"} | {name for name, w in zip(("wavelet_loss", "kc_loss", "cbc_loss"), weights) if w > 0}
    assert set(losses) == expected
    assert all(torch.isfinite(v) and v >= 0 for v in losses.values())
    assert (model.frequency_loss is None) == (not any(weights))


def test_scale_regularization_only_when_enabled(demo_train):
    model, dataset = make_model(demo_train, use_scale_regularization=True)
    model.train()
    model.set_step(10)
    with torch.no_grad():
        model.gauss_params["scales"][0] = torch.tensor([0.0, -5.0, -5.0])  # ratio e^5 > 10
    out = model.get_outputs(dataset.cameras[0])
    losses = model.get_loss_dict(out, {"image": dataset.image_uint8(0), "image_idx": 0})
    scales = model.scales.detach().exp()
    ratio = scales.amax(-1) / scales.amin(-1)
    assert torch.isclose(losses["scale_reg"], 0.1 * (ratio.clamp_min(10.0) - 10.0).mean())
    plain, _ = make_model(demo_train)
    plain.train()
    assert "scale_reg" not in plain.get_loss_dict(plain.get_outputs(dataset.cameras[0]),
                                                  {"image": dataset.image_uint8(0), "image_idx": 0})


def test_main_loss_is_splatfactos_formula(demo_train):
    from kornia.metrics import ssim as kornia_ssim

    model, dataset = make_model(demo_train)
    model.eval()  # fixed background: the oracle sees the same render
    with torch.no_grad():
        out = model.get_outputs(dataset.cameras[3])
        losses = model.get_loss_dict(out, {"image": dataset.image_uint8(3), "image_idx": 3})
    pred = out["rgb"].double().numpy()
    gt = dataset.image_uint8(3).double().numpy() / 255.0
    l1 = np.abs(pred - gt).mean()
    ssim = float(kornia_ssim(out["rgb"].permute(2, 0, 1)[None], dataset.image_float(3).permute(2, 0, 1)[None], 11).mean())
    assert np.isclose(float(losses["main_loss"]), 0.8 * l1 + 0.2 * (1 - ssim), rtol=1e-5)


def test_metrics_and_logging_kurtosis(demo_train):
    model, dataset = make_model(demo_train)
    model.eval()
    with torch.no_grad():
        out = model.get_outputs(dataset.cameras[1])
    batch = {"image": dataset.image_uint8(1), "image_idx": 1}
    plain = model.get_metrics_dict(out, batch)
    assert set(plain) == {"psnr", "gaussian_count"} and plain["gaussian_count"] == model.num_points
    mse = ((out["rgb"].double() - dataset.image_uint8(1).double() / 255) ** 2).mean()
    assert np.isclose(plain["psnr"], float(10 * torch.log10(1 / mse)), atol=1e-3)
    logged = model.get_metrics_dict(out, batch, with_kurtosis=True)
    assert len(logged["kurtosis_render"]) == 9 and len(logged["kurtosis_gt"]) == 9
    assert all(np.isfinite(logged["kurtosis_gt"]))


def test_logged_gt_kurtosis_reads_the_cached_target(demo_train, monkeypatch):
    """Once a training image's wavelet target is cached, logging its GT kurtosis runs no DWT of the GT, and the value
    equals scipy's kurtosis of PyWavelets' subbands of that image (channel-averaged)."""
    pywt = pytest.importorskip("pywt")
    from scipy.stats import kurtosis as scipy_kurtosis

    import kc_splatfacto.losses.frequency as frequency

    model, dataset = make_model(demo_train, frequency=FrequencyLossConfig())
    out = model.get_outputs(dataset.cameras[2])
    batch = {"image": dataset.image_uint8(2), "image_idx": 2}
    model.get_loss_dict(out, batch)  # caches the target
    calls = []
    real_dwt2 = frequency.dwt2
    monkeypatch.setattr(frequency, "dwt2", lambda *a, **k: calls.append(a[0].shape) or real_dwt2(*a, **k))
    logged = model.get_metrics_dict(out, batch, with_kurtosis=True)
    assert len(calls) == 1  # the render's DWT only
    gt = dataset.image_uint8(2).double().numpy() / 255
    expected = np.zeros(9)
    for c in range(3):
        bands = pywt.wavedec2(gt[..., c], "db3", mode="symmetric", level=3)[1:][::-1]  # finest first
        expected += [scipy_kurtosis(b.ravel(), fisher=True, bias=True) for level in bands for b in level]
    np.testing.assert_allclose(logged["kurtosis_gt"], expected / 3, rtol=1e-3, atol=1e-3)


def test_evaluate_split_matches_numpy_psnr_and_kornia_ssim(demo_train):
    from kornia.metrics import ssim as kornia_ssim

    from kc_splatfacto.engine.evaluation import evaluate_split

    model, dataset = make_model(demo_train)
    model.train()  # evaluate_split switches to eval mode and back
    result = evaluate_split(model, dataset)
    assert model.training
    assert result["num_images"] == len(dataset) == len(result["per_image"])
    from kc_splatfacto.lpips import lpips_available

    if lpips_available("alex") is None:
        assert result["lpips_net"] == "alex" and all(0 < r["lpips"] < 1 for r in result["per_image"])
        assert np.isclose(result["lpips"], np.mean([r["lpips"] for r in result["per_image"]]))
    else:
        assert result["lpips"] is None and result["lpips_unavailable"]
    model.eval()
    psnrs, ssims = [], []
    with torch.no_grad():
        for i in range(len(dataset)):
            pred = model.get_outputs(dataset.cameras[i])["rgb"]
            mse = ((pred.double().numpy() - dataset.image_uint8(i).numpy() / 255.0) ** 2).mean()
            psnrs.append(10 * np.log10(1 / mse))
            ssims.append(float(kornia_ssim(pred.permute(2, 0, 1)[None], dataset.image_float(i).permute(2, 0, 1)[None],
                                           11).mean()))
    np.testing.assert_allclose([r["psnr"] for r in result["per_image"]], psnrs, atol=1e-3)
    np.testing.assert_allclose([r["ssim"] for r in result["per_image"]], ssims, atol=1e-6)
    assert np.isclose(result["psnr"], np.mean(psnrs), atol=1e-3) and np.isclose(result["psnr_std"], np.std(psnrs), atol=1e-3)


def test_frequency_terms_equal_a_direct_frequency_loss_call(demo_train):
    # every frequency setting away from its default, so a field the model's config does not pass on changes the values
    from kc_splatfacto.losses.frequency import FrequencyLoss

    settings = dict(wavelet_weight=2e-3, kc_weight=3e-5, cbc_weight=4e-2, wave="db2", wavelet_levels=2,
                    wavelet_mode="periodization", wavelet_weighting="fine", kc_supervised=False,
                    cbc_supervised=False, cbc_correlation=True)
    model, dataset = make_model(demo_train, frequency=FrequencyLossConfig(**settings))
    model.eval()  # fixed background: the direct call sees the same composited GT
    assert model.frequency_loss.config == FrequencyLossConfig(**settings)
    out = model.get_outputs(dataset.cameras[2])
    losses = model.get_loss_dict(out, {"image": dataset.image_uint8(2), "image_idx": 2})
    direct_loss = FrequencyLoss(**settings)
    pred = out["rgb"].permute(2, 0, 1)[None]
    gt = (dataset.image_uint8(2).float() / 255.0).permute(2, 0, 1)[None]
    direct = direct_loss(pred, direct_loss.prepare_target(gt))
    assert set(direct) == {"wavelet_loss", "kc_loss", "cbc_loss"}
    for key, value in direct.items():
        torch.testing.assert_close(losses[key], value, rtol=1e-6, atol=0)
    # and the terms reach the render: the same gradient on it (a detached prediction has none)
    model_grad, = torch.autograd.grad(sum(losses[k] for k in direct), out["rgb"], retain_graph=True)
    direct_grad, = torch.autograd.grad(sum(direct.values()), out["rgb"])
    assert float(direct_grad.abs().max()) > 0
    torch.testing.assert_close(model_grad, direct_grad, rtol=1e-5, atol=1e-12)


@pytest.mark.parametrize("per_coefficient", [0.0, 0.5, 1.0, 2.0, 3.0])
@pytest.mark.parametrize("max_degree", [0, 1, 2, 3])
def test_sh_degree_for_views_is_the_largest_degree_with_enough_views_per_coefficient(per_coefficient, max_degree):
    config = SplatfactoModelConfig(sh_degree=max_degree, sh_views_per_coefficient=per_coefficient)
    for views in range(1, 60):
        if per_coefficient == 0:
            expected = max_degree  # the rule off: the configured degree whatever the views
        else:
            expected = max(d for d in range(max_degree + 1) if d == 0 or (d + 1) ** 2 * per_coefficient <= views)
        assert config.sh_degree_for_views(views) == expected, views


@pytest.mark.parametrize(("views", "degree"), [(12, 1), (5, 0), (40, 3)])
def test_views_cap_the_sh_coefficients_the_model_holds_and_renders(demo_train, views, degree):
    outputs, dataset = demo_train
    config = SplatfactoModelConfig(num_downscales=0, sh_views_per_coefficient=2.0)
    model = config.setup(scene_scale=outputs.scene_scale, num_train_data=views,
                         seed_points=(outputs.points3d_xyz, outputs.points3d_rgb))
    assert model.sh_degree == degree
    assert model.features_rest.shape[1] == (degree + 1) ** 2 - 1
    model.train()
    model.set_step(10**6)  # past every SH interval: the degree in use is the capped one
    assert model.sh_degree_to_use() == degree
    rgb = model.get_outputs(dataset.cameras[0])["rgb"]
    assert torch.isfinite(rgb).all()
    rgb.sum().backward()
    if degree > 0:
        assert model.features_rest.grad is not None and model.features_rest.grad.abs().sum() > 0


def _train_steps(model, dataset, steps, **batch_extra):
    """model.set_step / get_outputs / get_loss_dict of training image 0 at each step in ``steps``."""
    model.train()
    for step in steps:
        model.set_step(step)
        out = model.get_outputs(dataset.cameras[0])
        model.get_loss_dict(out, {"image": dataset.image_uint8(0), "image_idx": 0, **batch_extra})
    return out


def test_splatfacto_neither_warns_of_nor_transforms_for_a_wavelet_loss_it_does_not_have(demo_train, monkeypatch):
    """Issue 68: splatfacto (every frequency weight zero) at 1/4 resolution (16x12, too small for 3 db3 levels) says
    nothing about a FrequencyLoss and runs no DWT in its loss or its per-step metrics; only the logging steps'
    band kurtosis (the baseline of kc-bench's kurtosis-gap plots) transforms, silently."""
    import warnings

    import kc_splatfacto.losses.frequency as frequency
    import kc_splatfacto.losses.wavelets as wavelets

    outputs, dataset = demo_train
    model = SplatfactoModelConfig(num_downscales=2).setup(
        scene_scale=outputs.scene_scale, num_train_data=len(dataset),
        seed_points=(outputs.points3d_xyz, outputs.points3d_rgb))
    calls = []
    for module in (frequency, wavelets):
        real = module.dwt2
        monkeypatch.setattr(module, "dwt2", lambda *a, _real=real, **k: calls.append(a[0].shape) or _real(*a, **k))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = _train_steps(model, dataset, range(3))
        assert model.get_downscale_factor() == 4 and out["rgb"].shape == (12, 16, 3)
        batch = {"image": dataset.image_uint8(0), "image_idx": 0}
        with torch.no_grad():
            model.get_metrics_dict(out, batch)
        assert calls == []
        with torch.no_grad():
            logged = model.get_metrics_dict(out, batch, with_kurtosis=True)
    assert len(logged["kurtosis_render"]) == 3  # the one level 16x12 holds
    assert [str(w.message) for w in caught] == []


def test_kc_splatfacto_names_the_training_size_w_x_h_once_per_size(demo_train):
    """Issue 68: the warning about levels left out names the size trained at (W x H) as a fraction of the scene's,
    and the step from which every level fits; once per size, not once per step."""
    import warnings

    outputs, dataset = demo_train  # 64x48
    model = SplatfactoModelConfig(num_downscales=2, steps_scale=0.001, frequency=FrequencyLossConfig()).setup(
        scene_scale=outputs.scene_scale, num_train_data=len(dataset),
        seed_points=(outputs.points3d_xyz, outputs.points3d_rgb))
    period = model.schedule.resolution_schedule
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        _train_steps(model, dataset, [0, 1, period, period + 1, 2 * period, 2 * period + 1])
    assert [str(w.message) for w in caught] == [
        "FrequencyLoss: while training at 1/4 resolution (16x12 of 64x48) a db3 DWT supports only 1 of the 3 "
        f"requested levels; the 2 coarsest levels are left out until step {2 * period} (full resolution, 64x48)",
        "FrequencyLoss: while training at 1/2 resolution (32x24 of 64x48) a db3 DWT supports only 2 of the 3 "
        f"requested levels; the coarsest level is left out until step {2 * period} (full resolution, 64x48)",
    ]
