"""Stiff and extreme inputs for the DWT and the frequency losses: one test per case (docs/stability.md lists them)."""

import warnings

import numpy as np
import pytest
import scipy.stats
import torch

from kc_splatfacto.losses import (
    FrequencyLoss,
    band_kurtosis,
    cbc_loss,
    dwt2,
    kc_loss,
    prepare_target,
    wavelet_bands,
)
from tests.losses.test_frequency import blur, load_image

ALL_TERMS = {"wavelet_loss", "kc_loss", "cbc_loss"}


def all_terms(pred, gt, **options):
    """Every term with unit weights (plus the unsupervised and correlation variants), and pred's gradient."""
    pred = pred.detach().clone().requires_grad_(True)
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1.0, **options)
    terms = dict(loss(pred, loss.prepare_target(gt)))
    terms["kc_unsupervised"] = kc_loss(wavelet_bands(pred), kc_supervised=False)
    terms["cbc_unsupervised"] = cbc_loss(wavelet_bands(pred), cbc_supervised=False)
    terms["cbc_correlation"] = cbc_loss(wavelet_bands(pred, cbc_correlation=True), prepare_target(gt, cbc_correlation=True))
    sum(terms.values()).backward()
    return {k: v.detach() for k, v in terms.items()}, pred.grad


def assert_finite(terms, grad):
    for key, value in terms.items():
        assert bool(torch.isfinite(value).all()), f"{key} = {value}"
    assert grad is not None and bool(torch.isfinite(grad).all())


@pytest.fixture
def photo(castle_p30):
    return load_image(castle_p30, size=(96, 64)).float()


def test_constant_images_give_finite_losses_and_gradients(photo):
    constant = torch.full_like(photo, 0.5)
    black = torch.zeros_like(photo)
    for pred, gt in [(constant, photo), (photo, constant), (constant, torch.full_like(photo, 0.2)), (black, black)]:
        terms, grad = all_terms(pred, gt)
        assert_finite(terms, grad)
    # a constant band has kurtosis -3 (eps on the variance), never NaN
    kurtosis = band_kurtosis(dwt2(constant))
    torch.testing.assert_close(kurtosis, torch.full_like(kurtosis, -3.0), rtol=0, atol=1e-6)


@pytest.mark.parametrize("mode", ["symmetric", "reflect", "zero", "periodization"])
def test_pred_equal_gt_gives_exactly_zero_and_finite_gradients(photo, mode):
    terms, grad = all_terms(photo, photo, wavelet_mode=mode)
    for key in ALL_TERMS:
        assert float(terms[key]) == 0.0, key
    assert_finite(terms, grad)
    cached = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1.0, wavelet_mode=mode)
    assert all(float(v) == 0.0 for v in cached(photo, cached.prepare_target(photo)).values())


@pytest.mark.parametrize("size", [1, 3])
def test_tiny_images_give_zero_finite_losses_with_one_warning(size):
    pred = torch.rand(2, 3, size, size)
    gt = torch.rand(2, 3, size, size)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        terms, grad = all_terms(pred, gt)
    assert any(f"{size}x{size}" in str(w.message) for w in caught)
    assert_finite(terms, grad)
    assert set(terms) >= ALL_TERMS
    assert all(float(v) == 0.0 for v in terms.values())
    assert bool((grad == 0).all())


def test_small_image_with_one_level_matches_pywt_statistics():
    # 10x10 supports one db3 level (pywt.dwt_max_level(10, 6) == 1): the statistics still agree with scipy
    import pywt

    rng = np.random.default_rng(5)
    image = rng.random((10, 10))
    with pytest.warns(UserWarning, match="10x10"):
        kurtosis = band_kurtosis(dwt2(torch.tensor(image)[None, None]))[0, 0].numpy()
    bands = pywt.wavedec2(image, "db3", mode="symmetric", level=1)[1]
    np.testing.assert_allclose(kurtosis, [scipy.stats.kurtosis(b.ravel()) for b in bands], rtol=1e-6)


@pytest.mark.parametrize("scale", [1e4, 1e-6])
def test_intensity_scale_changes_nothing_but_the_units(photo, scale):
    pred = blur(photo.double(), 1.0).float()
    base, _ = all_terms(pred, photo)
    scaled, scaled_grad = all_terms(pred * scale, photo * scale)
    assert_finite(scaled, scaled_grad)
    # kurtosis and correlation are scale-invariant; wavelet L1 is 1-homogeneous; covariance energy 4-homogeneous
    for key, power in [
        ("kc_loss", 0),
        ("kc_unsupervised", 0),
        ("cbc_correlation", 0),
        ("wavelet_loss", 1),
        ("cbc_loss", 4),
        ("cbc_unsupervised", 4),
    ]:
        np.testing.assert_allclose(float(scaled[key]), float(base[key]) * scale**power, rtol=2e-3, err_msg=key)
    k_base = band_kurtosis(dwt2(photo))
    k_scaled = band_kurtosis(dwt2(photo * scale))
    torch.testing.assert_close(k_scaled, k_base, rtol=1e-4, atol=1e-4)


def test_single_bright_pixel_reaches_maximal_kurtosis():
    # Haar, one pixel at an even position: each finest band holds exactly one non-zero among P coefficients, the
    # largest kurtosis P values can have: (P^2 - 3P + 3) / (P - 1) - 3
    image = torch.zeros(1, 1, 64, 64, dtype=torch.float64)
    image[..., 20, 32] = 1.0
    kurtosis = band_kurtosis(dwt2(image, wave="db1", levels=1))[0, 0]
    count = 32 * 32
    maximum = (count**2 - 3 * count + 3) / (count - 1) - 3
    torch.testing.assert_close(kurtosis, torch.full_like(kurtosis, maximum), rtol=1e-9, atol=0)
    # db3 in float32: the same extreme heavy tail, equal to scipy, and every loss stays finite
    image32 = image.float()
    coeffs = dwt2(image32)
    ours = band_kurtosis(coeffs)[0, 0].numpy()
    expected = [
        scipy.stats.kurtosis(level[0, 0, o].flatten().double().numpy()) for level in coeffs.details for o in range(3)
    ]
    np.testing.assert_allclose(ours, expected, rtol=1e-4)
    assert ours[:3].min() > 100
    terms, grad = all_terms(image32, torch.zeros_like(image32))
    assert_finite(terms, grad)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_pred_raises_naming_pred(bad):
    pred = torch.rand(1, 3, 48, 48)
    pred[0, 1, 5, 7] = bad
    gt = torch.rand(1, 3, 48, 48)
    loss = FrequencyLoss()
    with pytest.raises(ValueError, match="'pred'"):
        loss(pred, loss.prepare_target(gt))
    with pytest.raises(ValueError, match="'image'"):  # the functions' entry point: the bands of an image
        wavelet_bands(pred)


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_gt_raises_naming_gt(bad):
    gt = torch.rand(1, 3, 48, 48)
    gt[0, 0, 0, 0] = bad
    loss = FrequencyLoss()
    for call in (
        lambda: loss.prepare_target(gt),
        lambda: prepare_target(gt),
    ):
        with pytest.raises(ValueError, match="'gt'"):
            call()


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_precision_inputs(photo, half):
    pred = blur(photo.double(), 1.0).to(half).requires_grad_(True)
    gt = photo.to(half)
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1.0)
    terms = loss(pred, loss.prepare_target(gt))
    sum(terms.values()).backward()
    assert pred.grad.dtype == half and bool(torch.isfinite(pred.grad).all())
    # computed in float32: equal to the float32 computation on the same (rounded) values
    reference = loss(pred.detach().float(), loss.prepare_target(gt.float()))
    for key, value in terms.items():
        assert value.dtype == torch.float32
        torch.testing.assert_close(value.detach(), reference[key], rtol=1e-5, atol=0)


def test_paper_failure_weight_on_blurred_prediction_keeps_gradients_finite(photo):
    # kc weight 1e-3 (the supplementary table's divergent setting) on a heavily blurred render
    pred = blur(photo.double(), 3.0).float().requires_grad_(True)
    loss = FrequencyLoss(wavelet_weight=1e-3, kc_weight=1e-3, cbc_weight=1e-2)
    terms = loss(pred, loss.prepare_target(photo))
    sum(terms.values()).backward()
    assert bool(torch.isfinite(pred.grad).all())
    assert float(pred.grad.abs().max()) > 0
    # the gradient is bounded by the eps on the variance: nowhere near float32 overflow
    assert float(pred.grad.abs().max()) < 1e3
