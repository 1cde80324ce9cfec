"""The fused frequency terms (the torch path a GPU runs): the band slots against PyWavelets, the terms and their
gradient against the level-by-level path (itself held to PyWavelets and scipy in test_frequency.py) and against
finite differences, and the stiff cases of docs/stability.md."""

from __future__ import annotations

import numpy as np
import pytest
import pywt
import torch

from kc_splatfacto import backend
from kc_splatfacto.losses import FrequencyLoss
from kc_splatfacto.losses import _fused_frequency as fused
from tests.losses.test_frequency import blur, load_image

TERMS = ("wavelet_loss", "kc_loss", "cbc_loss")


@pytest.mark.parametrize("mode", ["symmetric", "reflect", "zero", "periodization"])
@pytest.mark.parametrize("wave,levels,size", [("db3", 3, (45, 61)), ("haar", 4, (32, 40)), ("db2", 2, (17, 30))])
def test_band_slots_are_pywavelets_coefficients_with_zeros_around(mode, wave, levels, size):
    rng = np.random.default_rng(0)
    image = rng.random((2, 3, *size))
    x = torch.from_numpy(image)
    plan = fused.plan_for(size, wave, mode, levels, x)
    slots = fused.band_slots(fused.as_planes(x), plan).permute(0, 1, 3, 2).numpy()  # [K, h, w, N]
    assert plan.levels == levels
    for n in range(6):
        coefficients = pywt.wavedec2(image.reshape(6, *size)[n], wave, mode=mode, level=levels)
        np.testing.assert_allclose(slots[-1, : coefficients[0].shape[0], : coefficients[0].shape[1], n],
                                   coefficients[0], rtol=0, atol=1e-12)
        for j in range(1, levels + 1):
            for o, band in enumerate(coefficients[-j]):  # (cH, cV, cD) of level j, finest first from the end
                slot = slots[o * levels + j - 1, ..., n]
                np.testing.assert_allclose(slot[: band.shape[0], : band.shape[1]], band, rtol=0, atol=1e-12)
                around = slot.copy()
                around[: band.shape[0], : band.shape[1]] = 0.0
                assert not around.any()


def terms_and_grad(loss: FrequencyLoss, pred: torch.Tensor, gt: torch.Tensor, fused_path: bool):
    loss.fused = fused_path
    with backend.torch_reference():
        x = pred.clone().requires_grad_(True)
        terms = loss(x, loss.prepare_target(gt))
        sum(terms.values()).backward()
    return {k: v.detach() for k, v in terms.items()}, x.grad


SETTINGS = [
    {},
    {"wavelet_mode": "zero"},
    {"wavelet_mode": "periodization", "wave": "haar", "wavelet_levels": 4},
    {"wavelet_mode": "reflect", "wavelet_weighting": "fine"},
    {"kc_weight": 0.0},
    {"cbc_weight": 0.0, "wavelet_weighting": "uniform"},
    {"wavelet_weight": 0.0},
]


@pytest.mark.parametrize("settings", SETTINGS)
@pytest.mark.parametrize("size", [(40, 56), (45, 61)])
def test_fused_terms_and_gradient_equal_the_level_by_level_path_in_float64(settings, size):
    g = torch.Generator().manual_seed(1)
    gt = torch.rand(2, 3, *size, generator=g, dtype=torch.float64) ** 3
    pred = torch.rand(2, 3, *size, generator=g, dtype=torch.float64) ** 2
    loss = FrequencyLoss(**{"wavelet_weight": 1.0, "kc_weight": 1.0, "cbc_weight": 1e3, **settings})
    reference, reference_grad = terms_and_grad(loss, pred, gt, fused_path=False)
    terms, grad = terms_and_grad(loss, pred, gt, fused_path=True)
    assert set(terms) == set(reference)
    for key in reference:
        torch.testing.assert_close(terms[key], reference[key], rtol=1e-11, atol=0)
    torch.testing.assert_close(grad, reference_grad, rtol=1e-9, atol=1e-12 * float(reference_grad.abs().max()))


def test_fused_terms_on_a_real_photo_in_float32(castle_p30):
    # training's precision and a render-like blurred prediction (small detail bands: the kurtosis's sensitive case)
    gt = load_image(castle_p30).float()
    pred = blur(gt, sigma=1.0) + 0.01 * torch.randn(gt.shape, generator=torch.Generator().manual_seed(3))
    loss = FrequencyLoss()  # the paper's weights
    reference, reference_grad = terms_and_grad(loss, pred, gt, fused_path=False)
    terms, grad = terms_and_grad(loss, pred, gt, fused_path=True)
    for key in TERMS:
        torch.testing.assert_close(terms[key], reference[key], rtol=2e-5, atol=0)
    scale = reference_grad.abs().max()
    torch.testing.assert_close(grad / scale, reference_grad / scale, rtol=0, atol=1e-5)


def test_fused_module_gradient_matches_finite_differences():
    g = torch.Generator().manual_seed(2)
    gt = torch.rand(2, 1, 20, 21, generator=g, dtype=torch.float64)
    pred = torch.rand(2, 1, 20, 21, generator=g, dtype=torch.float64, requires_grad=True)
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1e4, wavelet_levels=2)
    with backend.torch_reference():
        target = loss.prepare_target(gt)
        assert torch.autograd.gradcheck(lambda p: torch.stack(list(loss(p, target).values())), (pred,), eps=1e-6,
                                        atol=1e-6, rtol=1e-5, fast_mode=True)


def test_the_model_layout_and_a_half_precision_render_take_the_fused_path(monkeypatch):
    calls = []
    original = fused.FusedFrequencyTerms.apply
    monkeypatch.setattr(fused.FusedFrequencyTerms, "apply", lambda *args: calls.append(1) or original(*args))
    g = torch.Generator().manual_seed(5)
    render = torch.rand(48, 64, 3, generator=g)  # [H, W, 3] as the rasterizer returns it
    gt = torch.rand(1, 3, 48, 64, generator=g)
    loss = FrequencyLoss()
    with backend.torch_reference():
        target = loss.prepare_target(gt)
        full = loss(render.permute(2, 0, 1)[None], target)
        half = loss(render.half().permute(2, 0, 1)[None], target)
    assert len(calls) == 2
    loss.fused = False
    with backend.torch_reference():
        reference = loss(render.permute(2, 0, 1)[None], target)
    for key in TERMS:
        torch.testing.assert_close(full[key], reference[key], rtol=1e-5, atol=0)
        torch.testing.assert_close(half[key], reference[key], rtol=5e-2, atol=0)  # the render rounded to float16


def test_the_compiled_cpu_path_never_takes_the_fused_function(monkeypatch):
    calls = []
    monkeypatch.setattr(fused.FusedFrequencyTerms, "apply", lambda *args: calls.append(1))
    pred, gt = torch.rand(1, 3, 40, 40), torch.rand(1, 3, 40, 40)
    loss = FrequencyLoss()
    assert set(loss(pred, loss.prepare_target(gt))) == set(TERMS)  # the CPU's compiled kernels
    assert calls == []


@pytest.mark.parametrize("settings,unfused", [({"kc_supervised": False}, "kc_loss"),
                                              ({"cbc_supervised": False}, "cbc_loss"),
                                              ({"cbc_correlation": True}, "cbc_loss")])
def test_a_variant_without_a_fused_kernel_runs_level_by_level_beside_the_fused_terms(settings, unfused, monkeypatch):
    calls = []
    original = fused.FusedFrequencyTerms.apply
    monkeypatch.setattr(fused.FusedFrequencyTerms, "apply", lambda *args: calls.append(args) or original(*args))
    g = torch.Generator().manual_seed(4)
    gt = torch.rand(2, 3, 40, 56, generator=g, dtype=torch.float64) ** 3
    pred = torch.rand(2, 3, 40, 56, generator=g, dtype=torch.float64) ** 2
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1e3, **settings)
    terms, grad = terms_and_grad(loss, pred, gt, fused_path=True)
    assert len(calls) == 1 and not loss.takes_fused_path(pred)
    _, _, _, l1_weights, kc_weight, cbc_weight = calls[0]
    # the Function computes the other two terms (the L1 always: it has no variant), not this one
    assert l1_weights is not None and (kc_weight == 0.0) == (unfused == "kc_loss")
    assert (cbc_weight == 0.0) == (unfused == "cbc_loss")
    reference, reference_grad = terms_and_grad(loss, pred, gt, fused_path=False)
    assert list(terms) == list(reference) == list(TERMS)
    for key in TERMS:
        torch.testing.assert_close(terms[key], reference[key], rtol=1e-11, atol=0)
    torch.testing.assert_close(grad, reference_grad, rtol=1e-9, atol=1e-12 * float(reference_grad.abs().max()))


def scaled(image: torch.Tensor, factor: float) -> torch.Tensor:
    return image * factor


@pytest.mark.parametrize("case", ["constant", "black", "saturated", "equal", "bright x1e4", "dim x1e-6", "tiny"])
def test_stiff_cases_give_finite_terms_equal_to_the_level_by_level_path(castle_p30, case):
    photo = load_image(castle_p30, size=(96, 64)).float()
    pairs = {
        "constant": (torch.full_like(photo, 0.5), photo),
        "black": (torch.zeros_like(photo), torch.zeros_like(photo)),
        "saturated": (torch.ones_like(photo), photo.clamp(0.5, 1.0)),
        "equal": (photo, photo),
        "bright x1e4": (scaled(blur(photo), 1e4), scaled(photo, 1e4)),
        "dim x1e-6": (scaled(blur(photo), 1e-6), scaled(photo, 1e-6)),
        "tiny": (photo[..., :9, :11], blur(photo)[..., :9, :11]),  # too small for a db3 level: no band
    }
    pred, gt = pairs[case]
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1.0)
    with pytest.warns(UserWarning) if case == "tiny" else _no_warning():
        terms, grad = terms_and_grad(loss, pred, gt, fused_path=True)
    reference, reference_grad = terms_and_grad(loss, pred, gt, fused_path=False)
    for key in TERMS:
        assert bool(torch.isfinite(terms[key])), (key, terms[key])
        torch.testing.assert_close(terms[key], reference[key], rtol=1e-4, atol=1e-6)
    assert bool(torch.isfinite(grad).all())
    if case in ("constant", "saturated"):
        # every band of the constant render is rounding noise of kurtosis ~-3: which band holds the spread's maximum
        # (and so takes its gradient) is decided by rounding, differently in each path; the terms agree
        return
    scale = max(float(reference_grad.abs().max()), 1e-30)
    torch.testing.assert_close(grad / scale, reference_grad / scale, rtol=0, atol=1e-4)
    if case == "equal":
        assert all(float(terms[key]) == 0.0 for key in TERMS)
        assert not grad.any()


class _no_warning:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (the GPU campaign runs it)")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_fused_terms_on_cuda_equal_the_cpu_path(dtype):
    # what a GPU trains with (the fused Function, TF32 kept off) against the CPU's compiled kernels
    g = torch.Generator().manual_seed(7)
    gt = torch.rand(1, 3, 96, 128, generator=g, dtype=dtype) ** 2
    pred = torch.rand(1, 3, 96, 128, generator=g, dtype=dtype)
    loss = FrequencyLoss(wavelet_weight=1.0, kc_weight=1.0, cbc_weight=1e3)
    results = []
    for device in ("cpu", "cuda"):
        x = pred.to(device).requires_grad_(True)
        terms = loss(x, loss.prepare_target(gt.to(device)))
        grad = torch.autograd.grad(torch.stack(list(terms.values())).sum(), x)[0]
        results.append(({k: v.detach().cpu() for k, v in terms.items()}, grad.cpu()))
    (cpu, cpu_grad), (cuda, cuda_grad) = results
    rtol = 1e-10 if dtype == torch.float64 else 1e-4
    for key in cpu:
        torch.testing.assert_close(cuda[key], cpu[key], rtol=rtol, atol=0)
    scale = cpu_grad.abs().max()
    torch.testing.assert_close(cuda_grad / scale, cpu_grad / scale, rtol=0, atol=rtol)
