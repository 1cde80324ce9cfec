"""The low-pass wavelet terms (the approximation bands' L1, the finest diagonal band's sparsity) against PyWavelets in
float64, finite differences and the stiff cases of docs/stability.md; the registered method that uses them."""

from __future__ import annotations

import numpy as np
import pytest
import pywt
import torch

from kc_splatfacto import backend
from kc_splatfacto.losses import FrequencyLoss, FrequencyLossConfig, diagonal_sparsity, dwt2, lowpass_l1, wavelet_bands
from kc_splatfacto.losses.frequency import prepare_target


def _pair(shape=(2, 3, 61, 80), seed=0):
    rng = np.random.default_rng(seed)
    gt = rng.random(shape)
    return np.clip(gt + 0.2 * rng.standard_normal(shape), 0, 1), gt


def _approximations(image: np.ndarray, wave: str, mode: str, levels: int) -> list[np.ndarray]:
    """PyWavelets' approximation band of each level j = 1..levels (a j-level decomposition's first array)."""
    return [pywt.wavedec2(image, wave, mode=mode, level=j, axes=(-2, -1))[0] for j in range(1, levels + 1)]


@pytest.mark.parametrize("wave,mode,levels", [("db3", "symmetric", 3), ("haar", "periodization", 2),
                                              ("db2", "zero", 2)])
def test_every_levels_approximation_is_pywavelets(wave, mode, levels):
    _, image = _pair()
    coeffs = dwt2(torch.from_numpy(image), wave, levels, mode)
    expected = _approximations(image, wave, mode, levels)
    assert len(coeffs.approximations) == levels
    for ours, theirs in zip(coeffs.approximations, expected):
        np.testing.assert_allclose(ours.numpy(), theirs, rtol=0, atol=1e-12)
    assert coeffs.approximations[-1] is coeffs.approx or torch.equal(coeffs.approximations[-1], coeffs.approx)


@pytest.mark.parametrize("weighting,weights", [("halving", [1.0, 0.5, 0.25]), ("uniform", [1.0, 1.0, 1.0])])
def test_lowpass_l1_and_diagonal_sparsity_match_pywavelets(weighting, weights):
    pred, gt = _pair(seed=1)
    pred_bands, gt_bands = wavelet_bands(torch.from_numpy(pred)), prepare_target(torch.from_numpy(gt))
    expected = sum(w * np.abs(a - b).mean() for w, a, b in zip(weights, _approximations(pred, "db3", "symmetric", 3),
                                                                 _approximations(gt, "db3", "symmetric", 3)))
    np.testing.assert_allclose(float(lowpass_l1(pred_bands, gt_bands, weighting)), expected, rtol=1e-12)
    finest_diagonal = pywt.wavedec2(pred, "db3", mode="symmetric", level=1, axes=(-2, -1))[1][2]
    np.testing.assert_allclose(float(diagonal_sparsity(pred_bands)), np.abs(finest_diagonal).mean(), rtol=1e-12)


@pytest.mark.parametrize("term", ["lowpass", "sparsity"])
def test_gradients_match_finite_differences(term):
    pred, gt = (torch.from_numpy(a) for a in _pair(shape=(1, 2, 19, 23), seed=2))
    loss = FrequencyLoss(**{**{name: 0.0 for name in ("wavelet_weight", "kc_weight", "cbc_weight")},
                            f"{term}_weight": 1.0, "wavelet_levels": 2})
    target = loss.prepare_target(gt)
    assert torch.autograd.gradcheck(lambda p: torch.stack(list(loss(p, target).values())),
                                    (pred.clone().requires_grad_(True),), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_the_terms_join_the_loss_by_their_weights_on_both_paths():
    pred, gt = (torch.from_numpy(a).float() for a in _pair(seed=3))
    config = FrequencyLossConfig(lowpass_weight=0.7, sparsity_weight=0.3)  # with the paper's three terms
    loss = config.setup()
    target = loss.prepare_target(gt)
    terms = loss(pred, target)
    assert set(terms) == {"wavelet_loss", "kc_loss", "cbc_loss", "lowpass_loss", "sparsity_loss"}
    bands = wavelet_bands(pred)
    torch.testing.assert_close(terms["lowpass_loss"], 0.7 * lowpass_l1(bands, target), rtol=1e-6, atol=0)
    torch.testing.assert_close(terms["sparsity_loss"], 0.3 * diagonal_sparsity(bands), rtol=1e-6, atol=0)
    with backend.torch_reference():  # the level-by-level torch path serves them (the fused one does not know them)
        reference = loss(pred, loss.prepare_target(gt))
    for name in terms:
        torch.testing.assert_close(terms[name], reference[name], rtol=1e-5, atol=0)


@pytest.mark.parametrize("case", ["constant", "black", "saturated", "equal", "tiny"])
def test_stiff_cases_give_finite_terms_and_gradients(case):
    pred, gt = (torch.from_numpy(a).float() for a in _pair(shape=(1, 3, 40, 48), seed=4))
    pairs = {"constant": (torch.full_like(pred, 0.5), gt), "black": (torch.zeros_like(pred), torch.zeros_like(gt)),
             "saturated": (torch.ones_like(pred), gt.clamp(0.5, 1.0)), "equal": (gt, gt),
             "tiny": (pred[..., :9, :11], gt[..., :9, :11])}
    pred, gt = pairs[case]
    loss = FrequencyLoss(lowpass_weight=1.0, sparsity_weight=1.0, wavelet_weight=0.0, kc_weight=0.0, cbc_weight=0.0)
    x = pred.clone().requires_grad_(True)
    with pytest.warns(UserWarning) if case == "tiny" else _quiet():
        terms = loss(x, loss.prepare_target(gt))
    torch.stack(list(terms.values())).sum().backward()
    assert all(bool(torch.isfinite(v)) for v in terms.values()) and bool(torch.isfinite(x.grad).all())
    if case in ("equal", "tiny"):
        assert float(terms["lowpass_loss"]) == 0.0
    if case == "tiny":
        assert float(terms["sparsity_loss"]) == 0.0 and not x.grad.any()


def test_splatfacto_lowpass_is_registered_with_the_published_defaults():
    from kc_splatfacto.registry import discover_methods

    config = discover_methods()["splatfacto-lowpass"].config.pipeline.model.frequency
    assert (config.lowpass_weight, config.lowpass_weighting, config.wave, config.wavelet_levels) == (
        1.0, "halving", "haar", 2)
    assert config.wavelet_weight == config.kc_weight == config.cbc_weight == config.sparsity_weight == 0.0


class _quiet:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
