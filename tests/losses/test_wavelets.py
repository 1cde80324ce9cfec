"""dwt2 against PyWavelets (filters, coefficients in every mode and size), gradients, level dropping, dtypes."""

import warnings

import numpy as np
import pytest
import pywt
import torch

from kc_splatfacto.losses.wavelets import MODES, daubechies_filters, dwt2, dwt_max_level

SIZES = [(1, 1), (7, 5), (64, 64), (255, 257)]
WAVES = ["db1", "db3", "db6"]


@pytest.mark.parametrize("order", range(1, 11))
def test_filters_match_pywt(order):
    dec_lo, dec_hi = daubechies_filters(f"db{order}")
    reference = pywt.Wavelet(f"db{order}")
    np.testing.assert_allclose(dec_lo, reference.dec_lo, rtol=0, atol=1e-12)
    np.testing.assert_allclose(dec_hi, reference.dec_hi, rtol=0, atol=1e-12)


def test_haar_alias_is_db1():
    for ours, theirs in zip(daubechies_filters("haar"), daubechies_filters("db1")):
        np.testing.assert_array_equal(ours, theirs)


@pytest.mark.parametrize("length", [1, 2, 5, 6, 7, 20, 64, 255, 1000])
@pytest.mark.parametrize("filter_len", [2, 6, 12])
def test_max_level_rule_matches_pywt(length, filter_len):
    assert dwt_max_level(length, filter_len) == pywt.dwt_max_level(length, filter_len)


@pytest.mark.parametrize("mode", MODES)
def test_coeff_length_matches_pywt(mode):
    from kc_splatfacto.losses.wavelets import coeff_length

    for length in (1, 2, 5, 6, 7, 64, 255, 257):
        for flen in (2, 6, 12):
            assert coeff_length(length, flen, mode) == pywt.dwt_coeff_len(length, flen, mode)


def _pywt_reference(images: np.ndarray, wave: str, mode: str, levels: int):
    """pywt.wavedec2 per image/channel, rearranged into (approx [B,C,h,w], details finest first [B,C,3,h,w])."""
    batch, channels = images.shape[:2]
    per = [[pywt.wavedec2(images[b, c], wave, mode=mode, level=levels) for c in range(channels)] for b in range(batch)]
    approx = np.stack([np.stack([per[b][c][0] for c in range(channels)]) for b in range(batch)])
    details = []
    for j in range(1, levels + 1):
        level = [[np.stack(per[b][c][-j]) for c in range(channels)] for b in range(batch)]
        details.append(np.stack([np.stack(row) for row in level]))
    return approx, details


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("wave", WAVES)
@pytest.mark.parametrize("dtype,atol", [(torch.float32, 1e-5), (torch.float64, 1e-10)], ids=["f32", "f64"])
def test_coefficients_match_pywt(wave, mode, size, dtype, atol):
    rng = np.random.default_rng(hash((wave, mode, size)) % 2**32)
    images = rng.random((2, 3, *size))  # two images, three channels: checks the batch/channel bookkeeping too
    requested = 3
    kept = min(requested, pywt.dwt_max_level(min(size), pywt.Wavelet(wave).dec_len))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        coeffs = dwt2(torch.tensor(images, dtype=dtype), wave=wave, levels=requested, mode=mode)
    assert len(caught) == (1 if kept < requested else 0)
    if kept < requested:
        assert f"{size[0]}x{size[1]}" in str(caught[0].message)
    assert coeffs.levels == kept
    approx, details = _pywt_reference(images, wave, mode, kept)
    assert coeffs.approx.dtype == dtype
    np.testing.assert_allclose(coeffs.approx.numpy(), approx, rtol=0, atol=atol)
    for ours, theirs in zip(coeffs.details, details):
        assert ours.shape == theirs.shape
        np.testing.assert_allclose(ours.numpy(), theirs, rtol=0, atol=atol)


@pytest.mark.parametrize("wave", ["db2", "db4", "db5", "db7", "db8"])
def test_other_orders_match_pywt(wave):
    rng = np.random.default_rng(1)
    image = rng.random((96, 80))
    levels = pywt.dwt_max_level(80, pywt.Wavelet(wave).dec_len)
    coeffs = dwt2(torch.tensor(image)[None, None], wave=wave, levels=levels, mode="symmetric")
    reference = pywt.wavedec2(image, wave, mode="symmetric", level=levels)
    np.testing.assert_allclose(coeffs.approx[0, 0].numpy(), reference[0], atol=1e-10, rtol=0)
    for j in range(levels):
        np.testing.assert_allclose(coeffs.details[j][0, 0].numpy(), np.stack(reference[-1 - j]), atol=1e-10, rtol=0)


@pytest.mark.parametrize("mode", MODES)
def test_gradcheck_float64(mode):
    torch.manual_seed(0)
    image = torch.rand(1, 2, 21, 20, dtype=torch.float64, requires_grad=True)

    def flat(x):
        coeffs = dwt2(x, wave="db3", levels=2, mode=mode)
        return torch.cat([coeffs.approx.flatten()] + [d.flatten() for d in coeffs.details])

    assert torch.autograd.gradcheck(flat, (image,), eps=1e-6, atol=1e-8)


def test_levels_dropped_warns_once_and_names_size():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        coeffs = dwt2(torch.rand(1, 3, 12, 40), wave="db3", levels=3)
    assert coeffs.levels == 1  # pywt.dwt_max_level(12, 6) == 1
    assert len(caught) == 1 and "12x40" in str(caught[0].message)


def test_no_level_left_returns_image_as_approx():
    image = torch.rand(2, 3, 1, 1)
    with pytest.warns(UserWarning, match="1x1"):
        coeffs = dwt2(image)
    assert coeffs.levels == 0
    torch.testing.assert_close(coeffs.approx, image, rtol=0, atol=0)


@pytest.mark.parametrize("half", [torch.float16, torch.bfloat16])
def test_half_inputs_are_transformed_in_float32(half):
    image = torch.rand(1, 3, 64, 64)
    low = image.to(half)
    coeffs = dwt2(low)
    reference = dwt2(low.float())
    assert coeffs.approx.dtype == torch.float32
    for ours, ref in zip(coeffs.details + [coeffs.approx], reference.details + [reference.approx]):
        torch.testing.assert_close(ours, ref, rtol=0, atol=0)


def test_orthogonal_transform_preserves_energy_in_periodization():
    image = torch.rand(1, 1, 64, 64, dtype=torch.float64)  # periodization + orthogonal filters: Parseval holds exactly
    coeffs = dwt2(image, wave="db3", levels=3, mode="periodization")
    energy = coeffs.approx.square().sum() + sum(d.square().sum() for d in coeffs.details)
    torch.testing.assert_close(energy, image.square().sum(), rtol=1e-12, atol=0)


def test_meta_device_shapes():
    coeffs = dwt2(torch.empty(2, 3, 256, 256, device="meta"), levels=3)
    assert coeffs.approx.device.type == "meta"
    assert [tuple(d.shape) for d in coeffs.details] == [(2, 3, 3, 130, 130), (2, 3, 3, 67, 67), (2, 3, 3, 36, 36)]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu():
    image = torch.rand(1, 3, 128, 96)
    cpu = dwt2(image)
    gpu = dwt2(image.cuda())
    for ours, ref in zip(gpu.details + [gpu.approx], cpu.details + [cpu.approx]):
        torch.testing.assert_close(ours.cpu(), ref, rtol=0, atol=1e-5)


@pytest.mark.parametrize(
    "kwargs,match",
    [({"wave": "sym4"}, "unknown wavelet"), ({"mode": "smooth"}, "unknown mode"), ({"levels": -1}, "levels")],
)
def test_bad_arguments_raise(kwargs, match):
    with pytest.raises(ValueError, match=match):
        dwt2(torch.rand(1, 1, 32, 32), **kwargs)


def test_bad_shape_raises():
    with pytest.raises(ValueError, match=r"\[B, C, H, W\]"):
        dwt2(torch.rand(32, 32))


@pytest.mark.parametrize("mode", ["reflect", "periodization"])
def test_fast_padding_equals_index_map_on_short_axes(mode):
    # the torch path (every device but the CPU) pads with F.pad when the extension fits the axis and with an index
    # gather otherwise; both must build the same extension (pywt's), including axes shorter than the filter
    from kc_splatfacto.losses.wavelets import _index_tensor, _pad

    for flen in (2, 6, 12):
        for height, width in [(1, 1), (2, 5), (5, 6), (11, 12), (13, 20)]:
            x = torch.rand(2, 1, height, width)
            rows = _index_tensor(height, flen, mode, x.device)
            cols = _index_tensor(width, flen, mode, x.device)
            torch.testing.assert_close(
                _pad(x, flen, mode), x.index_select(-2, rows).index_select(-1, cols), rtol=0, atol=0
            )


@pytest.mark.parametrize("mode", ["symmetric", "reflect", "periodization"])
def test_cpu_level_equals_torch_path(mode):
    # On CPU a level is two compiled separable passes and, backward, their adjoints gathered per image row
    # (_SeparableLevel); the torch path (_pad + the 2D bank's conv2d, autograd's backward) is the oracle: the same
    # coefficients and gradients to float64 rounding, for every filter length and for axes shorter than the extension
    # (odd ones included), with gradients flowing into both outputs (approx feeds the next level, details the losses).
    import torch.nn.functional as F

    from kc_splatfacto.losses.wavelets import _filter_bank, _level, _pad, filter_length

    torch.manual_seed(0)
    for wave in ("haar", "db3", "db6"):
        flen = filter_length(wave)
        bank = _filter_bank(wave, torch.float64, torch.device("cpu"))
        for height, width in [(1, 1), (2, 5), (5, 6), (11, 12), (13, 20), (37, 24)]:
            x = torch.rand(3, 1, height, width, dtype=torch.float64, requires_grad=True)
            approx, detail = _level(x, wave, flen, mode, bank)
            assert detail.is_contiguous() and approx.shape[1] == 1 and detail.shape[1] == 3
            ours = torch.cat([approx, detail], dim=1)
            reference = F.conv2d(_pad(x, flen, mode), bank, stride=2)
            torch.testing.assert_close(ours, reference, rtol=0, atol=1e-14)
            weights = torch.randn_like(ours)
            (grad,) = torch.autograd.grad((ours * weights).sum(), x)
            (grad_ref,) = torch.autograd.grad((reference * weights).sum(), x)
            torch.testing.assert_close(grad, grad_ref, rtol=0, atol=1e-12)
            # gradcheck of the compiled adjoint itself (not only agreement with autograd's conv backward)
            if height * width <= 60:
                assert torch.autograd.gradcheck(lambda t: torch.cat(_level(t, wave, flen, mode, bank), dim=1), (x,))  # noqa: B023 (called at once)


def test_cpu_level_results_do_not_depend_on_thread_count():
    import numba

    from kc_splatfacto.losses.frequency import FrequencyLoss

    torch.manual_seed(1)
    gt = torch.rand(1, 3, 64, 96)
    loss_fn = FrequencyLoss()
    target = loss_fn.prepare_target(gt)

    def run():
        pred = (gt + 0.05 * torch.randn(gt.shape, generator=torch.Generator().manual_seed(2))).requires_grad_()
        losses = loss_fn(pred, target)
        sum(losses.values()).backward()
        return [v.detach() for v in losses.values()], pred.grad

    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = run()
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = run()
    finally:
        numba.set_num_threads(before)
    for a, b in zip(single[0], many[0]):
        assert torch.equal(a, b)
    assert torch.equal(single[1], many[1])


def test_cpu_level_gradient_in_float32_matches_float64():
    # the float32 path (what training runs) against the float64 oracle: the summation order differs, not the result
    image = torch.rand(2, 3, 128, 192, dtype=torch.float64)
    weights = [torch.randn(2, 3, 3, h, w, dtype=torch.float64) for h, w in [(66, 98), (35, 51), (20, 28)]]

    def grad_of(dtype):
        x = image.to(dtype).requires_grad_()
        coeffs = dwt2(x, wave="db3", levels=3)
        total = sum((d * w.to(dtype)).sum() for d, w in zip(coeffs.details, weights))
        return torch.autograd.grad(total, x)[0].double()

    torch.testing.assert_close(grad_of(torch.float32), grad_of(torch.float64), rtol=0, atol=1e-5)
