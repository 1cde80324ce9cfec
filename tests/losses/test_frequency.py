"""Frequency losses against independent numpy / scipy / PyWavelets computations, and FrequencyLoss's contract."""

import warnings

import numpy as np
import pytest
import pywt
import scipy.stats
import torch
from kornia.filters import gaussian_blur2d

from kc_splatfacto import backend
from kc_splatfacto.losses import (
    FrequencyLoss,
    WaveletBands,
    band_kurtosis,
    cbc_loss,
    covariance_penalty,
    cross_band_covariance,
    dwt2,
    kc_loss,
    kurtosis_spread,
    level_weights,
    mean_band_kurtosis,
    prepare_target,
    wavelet_bands,
    wavelet_l1,
)


def load_image(scene_dir, name="0000.jpg", size=(192, 128)) -> torch.Tensor:
    """A real photo as [1, 3, H, W] float64 in [0, 1] (downscaled to keep tests fast)."""
    from PIL import Image

    with Image.open(scene_dir / "images" / name) as img:
        rgb = np.asarray(img.convert("RGB").resize(size, Image.BILINEAR), dtype=np.float64) / 255.0
    return torch.from_numpy(rgb).permute(2, 0, 1)[None].contiguous()


def blur(image: torch.Tensor, sigma: float = 1.5) -> torch.Tensor:
    """[B, C, H, W] blurred by a separable Gaussian of radius int(3 sigma), reflect borders."""
    size = 2 * int(3 * sigma) + 1
    return gaussian_blur2d(image, (size, size), (sigma, sigma), border_type="reflect")


def bands(image, **options) -> WaveletBands:
    """The differentiable WaveletBands of an image array or tensor (every statistic)."""
    return wavelet_bands(torch.as_tensor(image), **options)


def target(image, **options) -> WaveletBands:
    return prepare_target(torch.as_tensor(image), **options)


def pywt_bands(image: np.ndarray, wave="db3", mode="symmetric", levels=3):
    """[level][orientation] -> 2D array, finest first, from PyWavelets (the independent oracle)."""
    coeffs = pywt.wavedec2(image, wave, mode=mode, level=levels)
    return [list(coeffs[-j]) for j in range(1, levels + 1)]


# The paper's formulas (frequency.py's module docstring) in float64 numpy / scipy on PyWavelets' subbands: the oracles
# of the functions and of the module. Images are [B, C, H, W] arrays; statistics are per image and channel.


def per_channel(statistic, images: np.ndarray) -> np.ndarray:
    """[B, C, ...] of ``statistic`` applied to each [H, W] plane."""
    return np.array([[statistic(images[b, c]) for c in range(images.shape[1])] for b in range(images.shape[0])])


def oracle_kurtosis(image: np.ndarray) -> np.ndarray:
    """k_b of the 3J detail subbands (level-major H, V, D): scipy's biased Fisher kurtosis."""
    return np.array([scipy.stats.kurtosis(x.ravel(), fisher=True, bias=True) for lvl in pywt_bands(image) for x in lvl])


def oracle_l_cov(image: np.ndarray, correlation: bool = False) -> float:
    """L_cov = sum_j ||Sigma^j - diag(Sigma^j)||_F^2, Sigma^j numpy's covariance (or correlation) of (H, V, D)."""
    oracle = np.corrcoef if correlation else np.cov
    total = 0.0
    for level in pywt_bands(image):
        cov = oracle(np.stack([x.ravel() for x in level]))
        total += np.sum((cov - np.diag(np.diag(cov))) ** 2)
    return total


def oracle_wavelet_l1(pred: np.ndarray, gt: np.ndarray, weighting: str = "paper", levels: int = 3) -> float:
    """sum_j w_j sum_o mean|c^j_o(pred) - c^j_o(gt)|, the mean over images, channels and coefficients."""
    weights = {"paper": [2.0**j for j in range(1, levels + 1)], "fine": [2.0 ** (levels - j + 1) for j in
               range(1, levels + 1)], "uniform": [1.0] * levels}[weighting]
    planes = [(pywt_bands(pred[b, c], levels=levels), pywt_bands(gt[b, c], levels=levels))
              for b in range(pred.shape[0]) for c in range(pred.shape[1])]
    return sum(weights[j] * np.mean(np.stack([np.abs(p[j][o] - g[j][o]) for p, g in planes]))
               for j in range(levels) for o in range(3))


def oracle_kc(pred: np.ndarray, gt: np.ndarray | None = None) -> float:
    """|spread(pred) - spread(gt)| + sum_b |k_b(pred) - k_b(gt)| (gt None: spread(pred)), averaged."""
    kp = per_channel(oracle_kurtosis, pred)
    if gt is None:
        return float(np.ptp(kp, axis=-1).mean())
    kg = per_channel(oracle_kurtosis, gt)
    return float((np.abs(np.ptp(kp, axis=-1) - np.ptp(kg, axis=-1)) + np.abs(kp - kg).sum(axis=-1)).mean())


def oracle_cbc(pred: np.ndarray, gt: np.ndarray | None = None, correlation: bool = False) -> float:
    """|L_cov(pred) - L_cov(gt)| (gt None: L_cov(pred)), averaged."""
    lp = per_channel(lambda x: oracle_l_cov(x, correlation), pred)
    if gt is None:
        return float(lp.mean())
    return float(np.abs(lp - per_channel(lambda x: oracle_l_cov(x, correlation), gt)).mean())


def test_level_weights():
    assert level_weights(3, "paper") == [2.0, 4.0, 8.0]
    assert level_weights(3, "fine") == [8.0, 4.0, 2.0]
    assert level_weights(3, "uniform") == [1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match="weighting"):
        level_weights(3, "coarse")


@pytest.mark.parametrize("weighting", ["paper", "fine", "uniform"])
def test_wavelet_l1_matches_numpy(heavy_tailed_pair, weighting):
    pred, gt = heavy_tailed_pair
    weights = {"paper": [2, 4, 8], "fine": [8, 4, 2], "uniform": [1, 1, 1]}[weighting]
    expected = 0.0
    for j in range(3):
        for o in range(3):
            diffs = [
                np.abs(pywt_bands(pred[b, c])[j][o] - pywt_bands(gt[b, c])[j][o]) for b in range(2) for c in range(3)
            ]
            expected += weights[j] * np.mean(np.stack(diffs))
    ours = wavelet_l1(bands(pred), target(gt), wavelet_weighting=weighting)
    assert abs(float(ours) - expected) <= 1e-10 * expected


def test_band_kurtosis_matches_scipy(heavy_tailed_pair):
    pred, _ = heavy_tailed_pair
    ours = band_kurtosis(dwt2(torch.tensor(pred))).numpy()
    assert ours.shape == (2, 3, 9)
    for b in range(2):
        for c in range(3):
            bands = pywt_bands(pred[b, c])
            expected = [
                scipy.stats.kurtosis(bands[j][o].ravel(), fisher=True, bias=True) for j in range(3) for o in range(3)
            ]
            np.testing.assert_allclose(ours[b, c], expected, rtol=1e-4)
    assert ours[..., :3].min() > 0.5  # really heavy-tailed data (the finest bands have the most samples)


def test_band_kurtosis_float32_matches_scipy_on_real_image(castle_p30):
    image = load_image(castle_p30)
    ours = band_kurtosis(dwt2(image.float())).numpy()
    for c in range(3):
        bands = pywt_bands(image[0, c].numpy())
        expected = [
            scipy.stats.kurtosis(bands[j][o].ravel(), fisher=True, bias=True) for j in range(3) for o in range(3)
        ]
        np.testing.assert_allclose(ours[0, c], expected, rtol=1e-4)


def test_kurtosis_spread():
    kurtosis = torch.tensor([[[1.0, 5.0, -2.0], [0.0, 0.0, 0.0]]])
    torch.testing.assert_close(kurtosis_spread(kurtosis), torch.tensor([[7.0, 0.0]]))


def test_kc_loss_matches_scipy_formula(heavy_tailed_pair):
    pred, gt = heavy_tailed_pair
    per_image = []
    for b in range(2):
        for c in range(3):
            kp = np.array([scipy.stats.kurtosis(x.ravel()) for lvl in pywt_bands(pred[b, c]) for x in lvl])
            kg = np.array([scipy.stats.kurtosis(x.ravel()) for lvl in pywt_bands(gt[b, c]) for x in lvl])
            spread_p, spread_g = kp.max() - kp.min(), kg.max() - kg.min()
            per_image.append(abs(spread_p - spread_g) + np.abs(kp - kg).sum())
    expected = np.mean(per_image)
    ours = kc_loss(bands(pred), target(gt))
    np.testing.assert_allclose(float(ours), expected, rtol=1e-6)
    unsupervised = kc_loss(bands(pred), kc_supervised=False)
    spreads = [
        np.ptp([scipy.stats.kurtosis(x.ravel()) for lvl in pywt_bands(pred[b, c]) for x in lvl])
        for b in range(2)
        for c in range(3)
    ]
    np.testing.assert_allclose(float(unsupervised), np.mean(spreads), rtol=1e-6)


@pytest.mark.parametrize("correlation", [False, True])
def test_cross_band_covariance_matches_numpy(heavy_tailed_pair, correlation):
    pred, _ = heavy_tailed_pair
    ours = cross_band_covariance(dwt2(torch.tensor(pred)), correlation=correlation)
    oracle = np.corrcoef if correlation else np.cov
    for b in range(2):
        for c in range(3):
            for j, level in enumerate(pywt_bands(pred[b, c])):
                expected = oracle(np.stack([x.ravel() for x in level]))
                np.testing.assert_allclose(ours[j][b, c].numpy(), expected, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("correlation", [False, True])
def test_cbc_loss_matches_numpy(heavy_tailed_pair, correlation):
    pred, gt = heavy_tailed_pair
    oracle = np.corrcoef if correlation else np.cov

    def l_cov(image):
        total = 0.0
        for level in pywt_bands(image):
            cov = oracle(np.stack([x.ravel() for x in level]))
            total += np.sum((cov - np.diag(np.diag(cov))) ** 2)
        return total

    lp = np.array([[l_cov(pred[b, c]) for c in range(3)] for b in range(2)])
    lg = np.array([[l_cov(gt[b, c]) for c in range(3)] for b in range(2)])
    np.testing.assert_allclose(covariance_penalty(dwt2(torch.tensor(pred)), correlation).numpy(), lp, rtol=1e-6)
    ours = cbc_loss(bands(pred, cbc_correlation=correlation), target(gt, cbc_correlation=correlation))
    np.testing.assert_allclose(float(ours), np.mean(np.abs(lp - lg)), rtol=1e-6)
    unsupervised = cbc_loss(bands(pred, cbc_correlation=correlation), cbc_supervised=False)
    np.testing.assert_allclose(float(unsupervised), lp.mean(), rtol=1e-6)


def test_prepare_target_is_detached_and_holds_the_targets_bands_and_statistics(heavy_tailed_pair):
    _, gt = heavy_tailed_pair
    gt_t = torch.tensor(gt, requires_grad=True)
    prepared = prepare_target(gt_t)
    assert isinstance(prepared, WaveletBands)
    tensors = [prepared.coeffs.approx, *prepared.coeffs.details, prepared.kurtosis, prepared.spread, prepared.l_cov]
    assert not any(t.requires_grad for t in tensors)
    for b in range(gt.shape[0]):
        for c in range(gt.shape[1]):
            np.testing.assert_allclose(prepared.coeffs.approx[b, c].numpy(), pywt.wavedec2(gt[b, c], "db3",
                                       mode="symmetric", level=3)[0], rtol=0, atol=1e-12)
            for j, level in enumerate(pywt_bands(gt[b, c])):
                for o in range(3):
                    np.testing.assert_allclose(prepared.coeffs.details[j][b, c, o].numpy(), level[o], rtol=0, atol=1e-12)
    kurtosis = per_channel(oracle_kurtosis, gt)
    np.testing.assert_allclose(prepared.kurtosis.numpy(), kurtosis, rtol=1e-6)
    np.testing.assert_allclose(prepared.spread.numpy(), np.ptp(kurtosis, axis=-1), rtol=1e-6)
    np.testing.assert_allclose(prepared.l_cov.numpy(), per_channel(oracle_l_cov, gt), rtol=1e-6)


def test_frequency_loss_is_each_term_times_its_weight(heavy_tailed_pair):
    pred, gt = heavy_tailed_pair
    loss = FrequencyLoss(wavelet_weight=0.5, kc_weight=0.25, cbc_weight=2.0)
    out = loss(torch.tensor(pred), loss.prepare_target(torch.tensor(gt)))
    assert set(out) == {"wavelet_loss", "kc_loss", "cbc_loss"}
    np.testing.assert_allclose(float(out["wavelet_loss"]), 0.5 * oracle_wavelet_l1(pred, gt), rtol=1e-10)
    np.testing.assert_allclose(float(out["kc_loss"]), 0.25 * oracle_kc(pred, gt), rtol=1e-6)
    np.testing.assert_allclose(float(out["cbc_loss"]), 2.0 * oracle_cbc(pred, gt), rtol=1e-6)


def test_each_argument_takes_one_type(heavy_tailed_pair):
    pred, gt = (torch.tensor(a) for a in heavy_tailed_pair)
    with pytest.raises(TypeError, match="WaveletBands"):
        FrequencyLoss()(pred, gt)  # an image is not a target: prepare it once with prepare_target
    with pytest.raises(TypeError, match="WaveletBands"):
        kc_loss(pred, target(gt))
    with pytest.raises(ValueError, match="without 'kurtosis'"):
        kc_loss(bands(pred, kurtosis=False), target(gt))


@pytest.mark.parametrize(
    "weights,keys",
    [
        ((1e-3, 1e-5, 1e-2), {"wavelet_loss", "kc_loss", "cbc_loss"}),
        ((1e-3, 0.0, 0.0), {"wavelet_loss"}),
        ((0.0, 1e-5, 0.0), {"kc_loss"}),
        ((0.0, 0.0, 1e-2), {"cbc_loss"}),
        ((0.0, 0.0, 0.0), set()),
    ],
)
def test_frequency_loss_returns_only_active_terms(weights, keys):
    loss = FrequencyLoss(**dict(zip(("wavelet_weight", "kc_weight", "cbc_weight"), weights)))
    assert loss.active == bool(keys)
    out = loss(torch.rand(1, 3, 64, 64), loss.prepare_target(torch.rand(1, 3, 64, 64)))
    assert set(out) == keys


@pytest.mark.parametrize("bad", [-1e-3, float("nan"), float("inf")])
def test_bad_weight_is_refused(bad):
    with pytest.raises(ValueError, match="kc_weight"):
        FrequencyLoss(kc_weight=bad)


def test_frequency_loss_unsupervised_and_correlation_options(heavy_tailed_pair):
    pred, gt = heavy_tailed_pair
    loss = FrequencyLoss(wavelet_weight=0.0, kc_weight=1.0, cbc_weight=1.0, kc_supervised=False, cbc_supervised=False, cbc_correlation=True)
    out = loss(torch.tensor(pred), loss.prepare_target(torch.tensor(gt)))
    np.testing.assert_allclose(float(out["kc_loss"]), oracle_kc(pred), rtol=1e-6)
    np.testing.assert_allclose(float(out["cbc_loss"]), oracle_cbc(pred, correlation=True), rtol=1e-6)
    supervised = FrequencyLoss(wavelet_weight=0.0, kc_weight=0.0, cbc_weight=1.0, cbc_correlation=True)
    out = supervised(torch.tensor(pred), supervised.prepare_target(torch.tensor(gt)))
    np.testing.assert_allclose(float(out["cbc_loss"]), oracle_cbc(pred, gt, correlation=True), rtol=1e-6)


@pytest.mark.parametrize("weighting", ["paper", "fine", "uniform"])
def test_frequency_loss_weighting_option(heavy_tailed_pair, weighting):
    pred, gt = heavy_tailed_pair
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=0.0, cbc_weight=0.0, wavelet_weighting=weighting)
    out = loss(torch.tensor(pred), loss.prepare_target(torch.tensor(gt)))
    np.testing.assert_allclose(float(out["wavelet_loss"]), oracle_wavelet_l1(pred, gt, weighting), rtol=1e-10)


def test_float64_cached_target_serves_a_float32_prediction(heavy_tailed_pair):
    pred, gt = (torch.tensor(a) for a in heavy_tailed_pair)
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1.0)
    mixed = loss(pred.float(), loss.prepare_target(gt))  # target cached in float64
    same = loss(pred.float(), loss.prepare_target(gt.float()))
    for key, value in mixed.items():
        assert value.dtype == torch.float32
        torch.testing.assert_close(value, same[key], rtol=1e-4, atol=1e-7)


def test_target_with_other_settings_is_refused():
    gt = torch.rand(1, 3, 64, 64)
    zero_padded = FrequencyLoss(wavelet_mode="zero").prepare_target(gt)
    with pytest.raises(ValueError, match="prepare the target"):
        FrequencyLoss(wavelet_mode="symmetric")(torch.rand(1, 3, 64, 64), zero_padded)
    with pytest.raises(ValueError, match="same"):
        FrequencyLoss()(torch.rand(1, 3, 64, 32), FrequencyLoss().prepare_target(gt))
    pred = bands(torch.rand(1, 3, 64, 64))
    for call in (
        lambda: wavelet_l1(pred, zero_padded),
        lambda: kc_loss(pred, zero_padded),
        lambda: cbc_loss(bands(torch.rand(1, 3, 64, 64), wavelet_mode="zero", cbc_correlation=True), zero_padded),
    ):
        with pytest.raises(ValueError, match="prepare the target"):
            call()


def test_frequency_loss_falls_when_optimized(castle_p30):
    gt = load_image(castle_p30).float()
    pred = blur(gt, sigma=2.0).clone().requires_grad_(True)
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1e-2, cbc_weight=1e3)
    prepared = loss.prepare_target(gt)
    optimizer = torch.optim.Adam([pred], lr=1e-2)
    history = []
    for _ in range(60):
        terms = loss(pred, prepared)
        total = sum(terms.values())
        history.append({k: float(v.detach()) for k, v in terms.items()})
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
    for key in ("wavelet_loss", "kc_loss", "cbc_loss"):
        assert history[-1][key] < 0.75 * history[0][key], (key, history[0][key], history[-1][key])


def test_symmetric_padding_keeps_boundary_artifacts_out_of_blurred_kurtosis(castle_p30):
    # zero / periodization padding put a step at the border; on a blurred photo those border coefficients dominate
    # the finest bands and inflate their kurtosis, symmetric extension does not (docs/losses.md, padding table)
    blurred = blur(load_image(castle_p30), 1.5)
    finest = {mode: band_kurtosis(dwt2(blurred, mode=mode))[..., :3] for mode in ("symmetric", "zero", "periodization")}
    assert bool((finest["zero"] > 2 * finest["symmetric"]).all())
    assert bool((finest["periodization"] > 2 * finest["symmetric"]).all())


def test_mean_band_kurtosis_of_image_and_target(castle_p30):
    image = load_image(castle_p30)
    expected = per_channel(oracle_kurtosis, image.numpy()).mean(axis=(0, 1))  # float64 scipy on the same pixels
    from_image = mean_band_kurtosis(bands(image.float(), covariance=False))
    from_target = mean_band_kurtosis(FrequencyLoss().prepare_target(image.float()))
    assert len(from_image) == 9
    np.testing.assert_allclose(from_image, expected, rtol=1e-4)  # float32 statistics, as the trainer logs them
    np.testing.assert_allclose(from_target, expected, rtol=1e-4)


@pytest.mark.parametrize("term", ["kurtosis", "covariance", "correlation", "kc", "kc_unsupervised", "cbc", "module"])
def test_gradcheck_float64(term):
    # the band statistics have a hand-written backward: check it against finite differences
    torch.manual_seed(1)
    pred = torch.rand(2, 1, 20, 21, dtype=torch.float64, requires_grad=True)
    gt = torch.rand(2, 1, 20, 21, dtype=torch.float64)
    options = {"wavelet_levels": 2}
    functions = {
        "kurtosis": lambda p: band_kurtosis(dwt2(p, levels=2)),
        "covariance": lambda p: torch.stack(cross_band_covariance(dwt2(p, levels=2))),
        "correlation": lambda p: torch.stack(cross_band_covariance(dwt2(p, levels=2), correlation=True)),
        "kc": lambda p: kc_loss(bands(p, **options), target(gt, **options)),
        "kc_unsupervised": lambda p: kc_loss(bands(p, **options), kc_supervised=False),
        "cbc": lambda p: cbc_loss(bands(p, **options), target(gt, **options)) * 1e4,
        "module": lambda p: torch.stack(list(FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1e4, **options)(p, target(gt, **options)).values())),
    }
    # fast mode: the Jacobian against finite differences along random directions (full mode is ~10x slower)
    assert torch.autograd.gradcheck(functions[term], (pred,), eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


@pytest.mark.parametrize("correlation", [False, True])
def test_compiled_cpu_path_equals_torch_path(castle_p30, correlation):
    # On CPU the level, the moments and the L1 run as numba kernels (float64 sums); the torch path (what other devices
    # run) is the oracle: every term and the image gradient on a real photo in float32, training's precision and
    # size, with a render-like blurred prediction (small detail bands: the kurtosis's sensitive case)
    gt = load_image(castle_p30).float()
    pred = blur(gt, sigma=1.0) + 0.01 * torch.randn(gt.shape, generator=torch.Generator().manual_seed(3))
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1e3, cbc_correlation=correlation)

    def terms_and_grad():
        x = pred.clone().requires_grad_(True)
        terms = loss(x, loss.prepare_target(gt))
        sum(terms.values()).backward()
        return {k: v.detach() for k, v in terms.items()}, x.grad

    compiled, compiled_grad = terms_and_grad()
    with backend.torch_reference():
        reference, reference_grad = terms_and_grad()
    for key in reference:
        torch.testing.assert_close(compiled[key], reference[key], rtol=1e-5, atol=0)
    scale = reference_grad.abs().max()
    torch.testing.assert_close(compiled_grad / scale, reference_grad / scale, rtol=0, atol=1e-5)


def test_compiled_wavelet_l1_gradient_is_torch_l1_loss_including_ties():
    # sign(0) = 0, as torch's l1_loss backward: equal coefficients (a copied region) get no gradient
    torch.manual_seed(4)
    gt = torch.rand(1, 2, 40, 40)
    pred = gt.clone()
    pred[..., 20:, :] += 0.1 * torch.randn(1, 2, 20, 40)  # top half equal to gt: its fine bands tie exactly
    results = []
    for compiled in (True, False):
        x = pred.clone().requires_grad_(True)
        with backend.torch_reference(not compiled):
            value = wavelet_l1(bands(x), target(gt), "fine")
            value.backward()
        results.append((value.detach(), x.grad))
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-6, atol=0)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=0, atol=1e-7)


def test_too_small_an_image_is_said_once_per_size_w_x_h():
    """Issue 68: FrequencyLoss names the image W x H, once per size (a second visit of a size is silent), and not at
    all with ``warn_dropped_levels`` off (kc-train's model says it in its resolution schedule's terms)."""
    loss = FrequencyLoss()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for height, width in ((12, 40), (12, 40), (24, 40), (48, 40), (24, 40)):
            loss(torch.rand(1, 3, height, width), loss.prepare_target(torch.rand(1, 3, height, width)))
        quiet = FrequencyLoss()
        quiet.warn_dropped_levels = False
        quiet.prepare_target(torch.rand(1, 3, 12, 40))
    assert [str(w.message) for w in caught] == [
        "FrequencyLoss: a 40x12 image (W x H) supports only 1 of the 3 requested db3 levels; the 2 coarsest levels "
        "are left out at that size",
        "FrequencyLoss: a 40x24 image (W x H) supports only 2 of the 3 requested db3 levels; the coarsest level is "
        "left out at that size",
    ]
