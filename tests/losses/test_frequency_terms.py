"""The frequency loss as a table of terms, and ``FrequencyLoss.compare``: the one call a training loop makes per
image (compositing, mask and the cached ground-truth target owned by the loss)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import pywt
import torch

from kc_splatfacto import backend
from kc_splatfacto.losses import FrequencyLoss, FrequencyLossConfig, frequency
from kc_splatfacto.losses import _fused_frequency as fused
from kc_splatfacto.losses.frequency import TERMS, WEIGHTS, FrequencyTerm
from kc_splatfacto.settings import real, setting


def test_the_table_names_every_weight_field_and_decides_what_is_active():
    weight_fields = {f.name for f in dataclasses.fields(FrequencyLossConfig) if f.name.endswith("_weight")}
    assert set(WEIGHTS) == weight_fields and len(WEIGHTS) == len(TERMS)
    off = FrequencyLossConfig.off()
    assert all(getattr(off, name) == 0.0 for name in WEIGHTS) and not off.active
    for term in TERMS:
        only = dataclasses.replace(off, **{term.weight_field: 0.5})
        assert only.active and [(t.name, w) for t, w in only.active_terms()] == [(term.name, 0.5)]
        pred, gt = torch.rand(1, 3, 40, 40), torch.rand(1, 3, 40, 40)
        loss = only.setup()
        assert set(loss(pred, loss.prepare_target(gt))) == {term.name}


@dataclasses.dataclass
class WithEnergy(FrequencyLossConfig):
    """The paper's settings and a new term's weight, added as docs/architecture.md's recipe says."""

    energy_weight: float = setting(0.5, real(0.0))
    """weight of the squared difference of the finest detail bands (a term of the tests, with no fused kernel)"""


def finest_energy(pred, gt, config) -> torch.Tensor:
    """mean (c^1(pred) - c^1(gt))^2 over the finest level's three detail bands."""
    return (pred.coeffs.details[0] - gt.coeffs.details[0]).square().mean()


def add_energy_term(monkeypatch, fused_kernel: bool) -> None:
    """``energy_loss`` appended to the table (marked fused, or not)."""
    term = FrequencyTerm("energy_loss", "energy_weight", finest_energy, fused=(lambda c: True) if fused_kernel else None)
    monkeypatch.setattr(frequency, "TERMS", (*TERMS, term))


def energy_oracle(pred: np.ndarray, gt: np.ndarray, weight: float) -> float:
    """The new term by PyWavelets: [B, C, H, W] float64 images, db3, symmetric, 3 levels."""
    differences = []
    for p, g in zip(pred.reshape(-1, *pred.shape[-2:]), gt.reshape(-1, *gt.shape[-2:])):
        finest_p, finest_g = (pywt.wavedec2(x, "db3", mode="symmetric", level=3)[-1] for x in (p, g))
        differences += [bp - bg for bp, bg in zip(finest_p, finest_g)]
    return weight * float(np.mean(np.square(differences)))


@pytest.mark.parametrize("fused_path", [True, False])
def test_a_new_term_without_a_fused_kernel_runs_on_the_fast_and_the_slow_path(monkeypatch, fused_path):
    add_energy_term(monkeypatch, fused_kernel=False)
    calls = []
    original = fused.FusedFrequencyTerms.apply
    monkeypatch.setattr(fused.FusedFrequencyTerms, "apply", lambda *args: calls.append(1) or original(*args))
    g = torch.Generator().manual_seed(6)
    pred, gt = (torch.rand(1, 3, 40, 52, generator=g, dtype=torch.float64) for _ in range(2))
    loss = FrequencyLoss(WithEnergy())
    loss.fused = fused_path
    with backend.torch_reference():  # the torch path a GPU runs: the paper's three terms fused there
        terms = loss(pred, loss.prepare_target(gt))
    assert list(terms) == ["wavelet_loss", "kc_loss", "cbc_loss", "energy_loss"]
    assert len(calls) == int(fused_path)  # the three stay fused beside the new term
    np.testing.assert_allclose(float(terms["energy_loss"]), energy_oracle(pred.numpy(), gt.numpy(), 0.5), rtol=1e-10)
    paper = FrequencyLoss(WithEnergy(energy_weight=0.0))  # the paper's terms alone, level by level
    paper.fused = False
    expected = paper(pred, paper.prepare_target(gt))
    for name in expected:
        torch.testing.assert_close(terms[name], expected[name], rtol=1e-11, atol=0)


def test_a_new_term_marked_fused_without_a_kernel_is_refused_not_dropped(monkeypatch):
    add_energy_term(monkeypatch, fused_kernel=True)
    with pytest.raises(ValueError, match="'energy_loss' is marked fused.*fused=None"):
        FrequencyLoss(WithEnergy())


def _inputs(batch: int | None = None, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    lead = () if batch is None else (batch,)
    return torch.rand(*lead, 36, 52, 3, generator=g), torch.rand(*lead, 36, 52, 3, generator=g)


def _forward(loss: FrequencyLoss, render: torch.Tensor, gt: torch.Tensor) -> dict[str, torch.Tensor]:
    """The module called on [B, C, H, W] tensors built here by hand (numpy's transpose, not the loss's own)."""
    def bchw(x: torch.Tensor) -> torch.Tensor:
        array = x.numpy()
        array = array[None] if array.ndim == 3 else array
        return torch.from_numpy(np.ascontiguousarray(array.transpose(0, 3, 1, 2)))
    return loss(bchw(render), loss.prepare_target(bchw(gt)))


@pytest.mark.parametrize("batch", [None, 2])
def test_compare_is_the_module_on_channels_first_images(batch):
    render, gt = _inputs(batch)
    loss = FrequencyLoss()
    compared = loss.compare(render, gt, key="view")
    expected = _forward(loss, render, gt)
    assert set(compared) == set(expected)
    for name in expected:
        torch.testing.assert_close(compared[name], expected[name], rtol=1e-6, atol=0)


def test_compare_composites_rgba_over_the_background_and_applies_the_mask():
    render, gt = _inputs(seed=1)
    g = torch.Generator().manual_seed(2)
    alpha = torch.rand(36, 52, 1, generator=g)
    background = torch.tensor([0.2, 0.5, 0.7])
    mask = (torch.rand(36, 52, 1, generator=g) > 0.3).float()
    loss = FrequencyLoss()
    compared = loss.compare(render, torch.cat([gt, alpha], dim=-1), background=background, mask=mask)
    a, b, m = alpha.numpy(), background.numpy(), mask.numpy()
    composited = gt.numpy() * a + b * (1.0 - a)  # straight alpha over the background
    expected = _forward(loss, torch.from_numpy(render.numpy() * m), torch.from_numpy(composited * m))
    for name in expected:
        torch.testing.assert_close(compared[name], expected[name], rtol=1e-5, atol=0)
    with pytest.raises(ValueError, match="background"):
        loss.compare(render, torch.cat([gt, alpha], dim=-1))
    with pytest.raises(ValueError, match="same"):
        loss.compare(render, gt[:-1])


def test_compare_computes_a_keyed_target_once_and_an_unkeyed_one_every_time(monkeypatch):
    render, gt = _inputs(seed=3)
    loss = FrequencyLoss()
    calls = []
    original = loss.prepare_target
    monkeypatch.setattr(loss, "prepare_target", lambda image: calls.append(1) or original(image))
    first = loss.compare(render, gt, key=(4, 2))
    cached = loss.cached_target((4, 2))
    again = loss.compare(render, gt, key=(4, 2))
    assert len(calls) == 1 and loss.cached_target((4, 2)) is cached
    assert all(torch.equal(first[name], again[name]) for name in first)
    loss.compare(render, gt)
    loss.compare(render, gt)
    assert len(calls) == 3 and loss.cached_target(None) is None


def test_an_inactive_loss_compares_nothing():
    render, gt = _inputs()
    assert FrequencyLossConfig.off().setup().compare(render, gt, key=0) == {}
