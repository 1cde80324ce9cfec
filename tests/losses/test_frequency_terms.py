"""The frequency loss as a table of terms, and ``FrequencyLoss.compare``: the one call a training loop makes per
image (compositing, mask and the cached ground-truth target owned by the loss)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from kc_splatfacto.losses import FrequencyLoss, FrequencyLossConfig
from kc_splatfacto.losses.frequency import TERMS, WEIGHTS


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
