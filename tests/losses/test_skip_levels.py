"""The finest DWT levels left out of the frequency loss (``skip_finest_levels``, the scene plan's 'levels'), against
the paper's formulas on PyWavelets' levels skip+1..J (float64 numpy / scipy, as tests/losses/test_frequency.py)."""

import numpy as np
import pytest
import pywt
import scipy.stats
import torch

from kc_splatfacto import backend
from kc_splatfacto.losses import FrequencyLoss, FrequencyLossConfig
from kc_splatfacto.losses import _fused_frequency as fused


def kept_levels(image: np.ndarray, skip: int, levels: int = 3):
    """[level][orientation] of PyWavelets' db3 symmetric DWT, finest first, the ``skip`` finest left out."""
    coeffs = pywt.wavedec2(image, "db3", mode="symmetric", level=levels)
    return [list(coeffs[-j]) for j in range(1 + skip, levels + 1)]


def oracle_terms(pred: np.ndarray, gt: np.ndarray, skip: int) -> tuple[float, float, float]:
    """(wavelet L1 with the kept levels' own weights 2^j, supervised KC, supervised CBC) over levels skip+1..3."""
    weights = [2.0**j for j in range(1 + skip, 4)]
    planes = [(kept_levels(pred[b, c], skip), kept_levels(gt[b, c], skip))
              for b in range(pred.shape[0]) for c in range(pred.shape[1])]
    wavelet = sum(w * np.mean(np.stack([np.abs(p[j][o] - g[j][o]) for p, g in planes]))
                  for j, w in enumerate(weights) for o in range(3))
    kc, cbc = [], []
    for p, g in planes:
        kp = np.array([scipy.stats.kurtosis(x.ravel(), fisher=True, bias=True) for level in p for x in level])
        kg = np.array([scipy.stats.kurtosis(x.ravel(), fisher=True, bias=True) for level in g for x in level])
        kc.append(abs(np.ptp(kp) - np.ptp(kg)) + np.abs(kp - kg).sum())

        def l_cov(levels):
            total = 0.0
            for level in levels:
                cov = np.cov(np.stack([x.ravel() for x in level]))
                total += np.sum((cov - np.diag(np.diag(cov))) ** 2)
            return total

        cbc.append(abs(l_cov(p) - l_cov(g)))
    return float(wavelet), float(np.mean(kc)), float(np.mean(cbc))


@pytest.mark.parametrize("skip", [0, 1, 2])
def test_a_left_out_finest_level_is_in_no_term_and_the_kept_levels_keep_their_weights(heavy_tailed_pair, skip):
    pred, gt = heavy_tailed_pair
    loss = FrequencyLoss(wavelet_weight=0.5, kc_weight=0.25, cbc_weight=2.0, skip_finest_levels=skip)
    out = loss(torch.tensor(pred), loss.prepare_target(torch.tensor(gt)))
    wavelet, kc, cbc = oracle_terms(pred, gt, skip)
    np.testing.assert_allclose(float(out["wavelet_loss"]), 0.5 * wavelet, rtol=1e-10)
    np.testing.assert_allclose(float(out["kc_loss"]), 0.25 * kc, rtol=1e-6)
    np.testing.assert_allclose(float(out["cbc_loss"]), 2.0 * cbc, rtol=1e-6)


def test_a_render_wrong_only_in_its_finest_detail_costs_nothing_once_that_level_is_left_out(heavy_tailed_pair):
    """A render made by PyWavelets from the ground truth's coefficients with level 1's detail bands perturbed: the
    wavelet term that keeps level 1 sees the change, the one without it none (periodization: an orthogonal transform,
    so the coefficients round-trip exactly; symmetric extension's boundary coefficients do not)."""
    _, gt = heavy_tailed_pair
    image = torch.tensor(gt[:1])
    rng = np.random.default_rng(0)
    render = image.clone()
    for c in range(3):
        coeffs = pywt.wavedec2(gt[0, c], "db3", mode="periodization", level=3)
        coeffs[-1] = tuple(band + 0.05 * rng.standard_normal(band.shape) for band in coeffs[-1])
        render[0, c] = torch.tensor(pywt.waverec2(coeffs, "db3", mode="periodization"))
    terms = {}
    for skip in (0, 1):
        loss = FrequencyLoss(skip_finest_levels=skip, wavelet_mode="periodization")
        terms[skip] = {name: float(value) for name, value in loss(render, loss.prepare_target(image)).items()}
    assert terms[0]["wavelet_loss"] > 1e-4 and terms[0]["kc_loss"] > 1e-7
    assert all(value < 1e-12 for value in terms[1].values())


@pytest.mark.parametrize("downscale, skipped", [(1, 2), (2, 1), (4, 0), (8, 0)])
def test_a_warm_up_stage_leaves_out_one_level_fewer_per_halving(heavy_tailed_pair, downscale, skipped):
    pred, gt = heavy_tailed_pair
    loss = FrequencyLoss(wavelet_weight=0.5, kc_weight=0.25, cbc_weight=2.0, skip_finest_levels=2)
    loss.downscale = downscale
    assert loss.skipped_levels == skipped
    out = loss(torch.tensor(pred), loss.prepare_target(torch.tensor(gt)))
    np.testing.assert_allclose(float(out["wavelet_loss"]), 0.5 * oracle_terms(pred, gt, skipped)[0], rtol=1e-10)


def test_a_target_prepared_at_another_stage_is_refused(heavy_tailed_pair):
    pred, gt = heavy_tailed_pair
    loss = FrequencyLoss(skip_finest_levels=1)
    target = loss.prepare_target(torch.tensor(gt))
    loss.downscale = 2  # now every level is compared: the target's bands lack level 1
    with pytest.raises(ValueError, match="computed differently"):
        loss(torch.tensor(pred), target)


def test_the_fused_path_serves_only_where_every_level_is_compared(heavy_tailed_pair, monkeypatch):
    pred, gt = heavy_tailed_pair
    calls = []
    original = fused.FusedFrequencyTerms.apply
    monkeypatch.setattr(fused.FusedFrequencyTerms, "apply", lambda *args: calls.append(1) or original(*args))
    loss = FrequencyLoss(skip_finest_levels=1)
    with backend.torch_reference():
        full = loss(torch.tensor(pred), loss.prepare_target(torch.tensor(gt)))
        assert not calls and not loss.takes_fused_path(torch.tensor(pred))
        loss.downscale = 2
        assert loss.takes_fused_path(torch.tensor(pred))
        loss(torch.tensor(pred), loss.prepare_target(torch.tensor(gt)))
        assert calls
    np.testing.assert_allclose(float(full["wavelet_loss"]), 1e-3 * oracle_terms(pred, gt, 1)[0], rtol=1e-10)


def test_the_coarsest_level_is_always_compared():
    config = FrequencyLossConfig(skip_finest_levels=3)
    assert config.field_conflict()[0] == "skip_finest_levels"
    assert FrequencyLossConfig(skip_finest_levels=2).field_conflict() is None
    assert FrequencyLossConfig.off().__class__(**{**vars(FrequencyLossConfig.off()), "skip_finest_levels": 3}
                                               ).field_conflict() is None  # every weight 0: nothing is compared
