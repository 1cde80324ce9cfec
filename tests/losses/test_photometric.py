"""Photometric loss terms and metrics (kc_splatfacto.metrics) against independent numpy / scipy implementations."""

import numpy as np
import pytest
import scipy.ndimage
import torch

from kc_splatfacto.losses import dssim, l1
from kc_splatfacto.metrics import mean_ssim, psnr, ssim


def reference_ssim_map(x: np.ndarray, y: np.ndarray, window: int = 11, sigma: float = 1.5) -> np.ndarray:
    """Wang et al. SSIM map, Gaussian window, mirror ('reflect' in torch) borders, data range 1, float64."""
    radius = window // 2
    taps = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
    taps /= taps.sum()

    def smooth(a):
        out = scipy.ndimage.correlate1d(a, taps, axis=-1, mode="mirror")
        return scipy.ndimage.correlate1d(out, taps, axis=-2, mode="mirror")

    c1, c2 = 0.01**2, 0.03**2
    mu_x, mu_y = smooth(x), smooth(y)
    var_x = smooth(x * x) - mu_x**2
    var_y = smooth(y * y) - mu_y**2
    cov = smooth(x * y) - mu_x * mu_y
    return ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x**2 + mu_y**2 + c1) * (var_x + var_y + c2))


def reference_ssim(x: np.ndarray, y: np.ndarray, window: int = 11, sigma: float = 1.5) -> float:
    """The mean of :func:`reference_ssim_map` over everything."""
    return float(reference_ssim_map(x, y, window, sigma).mean())


@pytest.fixture
def image_pair():
    rng = np.random.default_rng(3)
    gt = rng.random((2, 3, 40, 33))
    pred = np.clip(gt + 0.1 * rng.standard_normal(gt.shape), 0, 1)
    return pred, gt


def test_ssim_matches_reference(image_pair):
    pred, gt = image_pair
    ssim_map = ssim(torch.tensor(pred), torch.tensor(gt))
    assert ssim_map.shape == pred.shape  # kornia's meaning: the map
    # pixel by pixel, borders included (kornia adds 1e-12 to the denominator: ~1e-10 relative on these images)
    np.testing.assert_allclose(ssim_map.numpy(), reference_ssim_map(pred, gt), rtol=1e-9, atol=0)
    ours = mean_ssim(torch.tensor(pred), torch.tensor(gt))
    assert ours.dim() == 0
    np.testing.assert_allclose(float(ours), reference_ssim(pred, gt), rtol=1e-6)


def test_ssim_on_real_photo(castle_p30):
    from PIL import Image

    with Image.open(castle_p30 / "images" / "0000.jpg") as img:
        gt = np.asarray(img.convert("RGB").resize((128, 96)), dtype=np.float32).transpose(2, 0, 1)[None] / 255.0
    pred = scipy.ndimage.uniform_filter(gt, size=(1, 1, 3, 3), mode="mirror")
    ours = float(mean_ssim(torch.tensor(pred), torch.tensor(gt)))
    np.testing.assert_allclose(ours, reference_ssim(pred.astype(np.float64), gt.astype(np.float64)), rtol=1e-4)
    assert 0.3 < ours < 0.99


def test_dssim_is_one_minus_ssim_not_kornia_loss(image_pair):
    from kornia.losses import ssim_loss

    pred, gt = (torch.tensor(a) for a in image_pair)
    torch.testing.assert_close(dssim(pred, gt), 1 - mean_ssim(pred, gt))
    # kornia's ssim_loss is (1 - SSIM) / 2: half of Splatfacto's term
    torch.testing.assert_close(ssim_loss(pred, gt, 11), dssim(pred, gt) / 2)


def test_ssim_of_identical_images_is_one(image_pair):
    _, gt = image_pair
    np.testing.assert_allclose(float(mean_ssim(torch.tensor(gt), torch.tensor(gt))), 1.0, atol=1e-9)


def test_psnr_matches_numpy(image_pair):
    pred, gt = image_pair
    expected = 10 * np.log10(1.0 / np.mean((pred - gt) ** 2))
    np.testing.assert_allclose(float(psnr(torch.tensor(pred), torch.tensor(gt))), expected, rtol=1e-6)
    assert float(psnr(torch.tensor(gt), torch.tensor(gt))) == float("inf")


def test_l1_matches_numpy_and_has_gradient(image_pair):
    pred, gt = image_pair
    pred_t = torch.tensor(pred, requires_grad=True)
    loss = l1(pred_t, torch.tensor(gt))
    np.testing.assert_allclose(float(loss.detach()), np.mean(np.abs(pred - gt)), rtol=1e-12)
    loss.backward()
    np.testing.assert_allclose(pred_t.grad.numpy(), np.sign(pred - gt) / pred.size, rtol=1e-12)


def test_ssim_is_differentiable_and_gradient_matches_finite_difference():
    torch.manual_seed(0)
    pred = torch.rand(1, 1, 16, 16, dtype=torch.float64, requires_grad=True)
    gt = torch.rand(1, 1, 16, 16, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda p: dssim(p, gt), (pred,), eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("fn", [l1, ssim, mean_ssim, dssim, psnr])
def test_shape_mismatch_raises(fn):
    with pytest.raises(ValueError, match="same shape"):
        fn(torch.rand(1, 3, 32, 32), torch.rand(1, 3, 32, 31))


def test_ssim_too_small_image_raises():
    with pytest.raises(ValueError, match="too small"):
        ssim(torch.rand(1, 3, 5, 40), torch.rand(1, 3, 5, 40))


def test_masked_psnr_counts_only_the_masked_pixels(image_pair):
    pred, gt = image_pair
    mask = np.zeros((2, 1, 40, 33), bool)
    mask[:, :, 5:30, 3:20] = True
    garbage = pred.copy()
    garbage[np.broadcast_to(~mask, pred.shape)] = 7.0  # outside the mask: ignored
    selected = np.broadcast_to(mask, pred.shape)
    expected = 10 * np.log10(1.0 / np.mean((pred[selected] - gt[selected]) ** 2))
    got = psnr(torch.tensor(garbage), torch.tensor(gt), mask=torch.tensor(mask))
    np.testing.assert_allclose(float(got), expected, rtol=1e-6)


def test_masked_mean_ssim_is_the_map_mean_over_the_mask(image_pair):
    pred, gt = (torch.tensor(a) for a in image_pair)
    mask = torch.zeros(2, 1, 40, 33, dtype=torch.bool)
    mask[:, :, 10:25, 8:30] = True
    ssim_map = ssim(pred, gt).numpy()
    expected = ssim_map[np.broadcast_to(mask.numpy(), ssim_map.shape)].mean()
    np.testing.assert_allclose(float(mean_ssim(pred, gt, mask=mask)), expected, rtol=1e-10)


def test_a_mask_that_selects_nothing_or_has_the_wrong_shape_is_an_error(image_pair):
    pred, gt = (torch.tensor(a) for a in image_pair)
    with pytest.raises(ValueError, match="selects no pixel"):
        psnr(pred, gt, mask=torch.zeros(2, 1, 40, 33, dtype=torch.bool))
    with pytest.raises(ValueError, match="mask must be"):
        mean_ssim(pred, gt, mask=torch.ones(2, 3, 40, 33, dtype=torch.bool))


# --- the fused CPU D-SSIM (losses/_ssim_kernels.py) against scipy and kornia --------------------------------------


def _kornia_dssim(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    return 1.0 - mean_ssim(pred, gt)


@pytest.mark.parametrize("shape", [(2, 3, 40, 33), (1, 1, 6, 6), (1, 3, 7, 11), (3, 2, 17, 6)])
def test_fused_dssim_matches_scipy_reference_in_float64(shape):
    rng = np.random.default_rng(sum(shape))
    gt = rng.random(shape)
    pred = np.clip(gt + 0.2 * rng.standard_normal(shape), 0, 1)
    got = dssim(torch.tensor(pred), torch.tensor(gt))
    assert got.grad_fn is None or "Fused" in type(got.grad_fn).__name__
    # kornia adds eps = 1e-12 to the denominator, the reference does not: ~1e-11 apart on these small images
    np.testing.assert_allclose(float(got), 1 - reference_ssim(pred, gt), rtol=0, atol=1e-10)


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
@pytest.mark.parametrize("shape", [(2, 3, 40, 33), (1, 1, 6, 9), (1, 3, 128, 64)])
def test_fused_dssim_value_and_gradient_match_kornia(dtype, rtol, shape):
    torch.manual_seed(sum(shape))
    gt = torch.rand(shape, dtype=dtype)
    pred = (gt + 0.2 * torch.randn(shape, dtype=dtype)).clamp(0, 1).requires_grad_(True)
    fused = dssim(pred, gt)
    assert "Fused" in type(fused.grad_fn).__name__  # the training loss takes the fused path on the CPU
    (g_fused,) = torch.autograd.grad(fused, pred)
    reference = _kornia_dssim(pred, gt)
    (g_reference,) = torch.autograd.grad(reference, pred)
    assert g_fused.dtype == dtype and g_fused.shape == pred.shape
    np.testing.assert_allclose(float(fused), float(reference), rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-13)
    scale = float(g_reference.abs().max())
    np.testing.assert_allclose(g_fused.numpy(), g_reference.numpy(), rtol=0, atol=rtol * scale)


def test_fused_dssim_upstream_gradient_scales_the_result():
    torch.manual_seed(1)
    gt = torch.rand(1, 3, 20, 24, dtype=torch.float64)
    pred = torch.rand(1, 3, 20, 24, dtype=torch.float64, requires_grad=True)
    (g1,) = torch.autograd.grad(dssim(pred, gt), pred)
    (g3,) = torch.autograd.grad(-3.0 * dssim(pred, gt), pred)
    np.testing.assert_allclose(g3.numpy(), -3.0 * g1.numpy(), rtol=1e-12)


def test_fused_dssim_does_not_depend_on_the_thread_count():
    import numba

    torch.manual_seed(2)
    gt = torch.rand(2, 3, 64, 48)
    pred = torch.rand(2, 3, 64, 48, requires_grad=True)
    before = numba.get_num_threads()
    results = []
    try:
        for threads in sorted({1, max(1, before)}):
            numba.set_num_threads(threads)
            value = dssim(pred, gt)
            (grad,) = torch.autograd.grad(value, pred)
            results.append((value.item(), grad.clone()))
    finally:
        numba.set_num_threads(before)
    for value, grad in results[1:]:
        assert value == results[0][0]
        assert torch.equal(grad, results[0][1])


def test_dssim_with_a_gt_that_needs_a_gradient_takes_kornia_and_gives_it_one():
    torch.manual_seed(3)
    gt = torch.rand(1, 3, 16, 16, dtype=torch.float64, requires_grad=True)
    pred = torch.rand(1, 3, 16, 16, dtype=torch.float64, requires_grad=True)
    value = dssim(pred, gt)
    assert "Fused" not in type(value.grad_fn).__name__
    g_pred, g_gt = torch.autograd.grad(value, (pred, gt))
    assert float(g_gt.abs().max()) > 0
    (g_fused,) = torch.autograd.grad(dssim(pred, gt.detach()), pred)
    np.testing.assert_allclose(g_fused.numpy(), g_pred.numpy(), rtol=1e-10, atol=1e-15)


def test_fused_dssim_of_identical_and_of_flat_images():
    from kc_splatfacto.metrics import SSIM_C1, SSIM_C2, SSIM_EPS

    flat = torch.full((1, 3, 12, 12), 0.25, dtype=torch.float64)
    # kornia's documented value for two identical flat images of value mu: 1 - SSIM = eps / ((2 mu^2 + c1) c2 + eps)
    expected = SSIM_EPS / ((2 * 0.25**2 + SSIM_C1) * SSIM_C2 + SSIM_EPS)
    np.testing.assert_allclose(float(dssim(flat, flat)), expected, rtol=0, atol=1e-15)  # 1 - mean: absolute
    img = torch.rand(1, 3, 12, 12, dtype=torch.float64, requires_grad=True)
    value = dssim(img, img.detach())
    (grad,) = torch.autograd.grad(value, img)
    reference = _kornia_dssim(img, img.detach())
    (g_reference,) = torch.autograd.grad(reference, img)
    assert 0 <= float(value) < 1e-9  # eps / den, as kornia's
    np.testing.assert_allclose(float(value), float(reference), rtol=0, atol=1e-15)
    np.testing.assert_allclose(grad.numpy(), g_reference.numpy(), rtol=0, atol=1e-15)  # at the minimum, ~0


# ------------------------------------------------------------------ the stacked D-SSIM (the torch path: a GPU's)


def _stacked_dssim(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    from kc_splatfacto import backend

    with backend.torch_reference():
        value = dssim(pred, gt)
    assert "Stacked" in type(value.grad_fn).__name__ or not pred.requires_grad
    return value


@pytest.mark.parametrize("shape", [(2, 3, 40, 33), (1, 1, 6, 6), (1, 3, 7, 11), (3, 2, 17, 6)])
def test_stacked_dssim_matches_scipy_reference_in_float64(shape):
    rng = np.random.default_rng(sum(shape) + 1)
    gt = rng.random(shape)
    pred = np.clip(gt + 0.2 * rng.standard_normal(shape), 0, 1)
    got = _stacked_dssim(torch.tensor(pred), torch.tensor(gt))
    np.testing.assert_allclose(float(got), 1 - reference_ssim(pred, gt), rtol=0, atol=1e-10)


@pytest.mark.parametrize("dtype, rtol", [(torch.float64, 1e-10), (torch.float32, 1e-4)])
@pytest.mark.parametrize("shape", [(2, 3, 40, 33), (1, 1, 6, 9), (1, 3, 128, 64)])
def test_stacked_dssim_value_and_gradient_match_kornia(dtype, rtol, shape):
    torch.manual_seed(sum(shape) + 1)
    gt = torch.rand(shape, dtype=dtype)
    pred = (gt + 0.2 * torch.randn(shape, dtype=dtype)).clamp(0, 1).requires_grad_(True)
    value = _stacked_dssim(pred, gt)
    (grad,) = torch.autograd.grad(value, pred)
    reference = _kornia_dssim(pred, gt)
    (g_reference,) = torch.autograd.grad(reference, pred)
    assert grad.dtype == dtype and grad.shape == pred.shape
    np.testing.assert_allclose(float(value), float(reference), rtol=0, atol=1e-6 if dtype == torch.float32 else 1e-13)
    np.testing.assert_allclose(grad.numpy(), g_reference.numpy(), rtol=0, atol=rtol * float(g_reference.abs().max()))


def test_stacked_dssim_of_a_render_in_its_layout_with_finite_differences_and_flat_images():
    from kc_splatfacto.metrics import SSIM_C1, SSIM_C2, SSIM_EPS

    torch.manual_seed(4)
    render = torch.rand(13, 15, 3, dtype=torch.float64, requires_grad=True)  # [H, W, 3], as the rasterizer returns it
    gt = torch.rand(1, 3, 13, 15, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda r: _stacked_dssim(r.permute(2, 0, 1)[None], gt), (render,), eps=1e-6,
                                    atol=1e-7, rtol=1e-5)
    flat = torch.full((1, 3, 12, 12), 0.25, dtype=torch.float64)
    expected = SSIM_EPS / ((2 * 0.25**2 + SSIM_C1) * SSIM_C2 + SSIM_EPS)
    np.testing.assert_allclose(float(_stacked_dssim(flat, flat)), expected, rtol=0, atol=1e-15)


def test_the_torch_path_of_the_main_loss_takes_a_third_of_kornias_operations():
    """L1 + D-SSIM as the model computes them on a GPU, forward and backward, counted as tensor operations (each a
    kernel launch on CUDA): ~59 on torch 2.13 (25 + 34), where kornia's SSIM under autograd took 121 (71 + 50)."""
    from kc_splatfacto import backend
    from tests.losses.test_frequency_launches import CountOps

    render = torch.rand(96, 128, 3, requires_grad=True)
    gt = torch.rand(1, 3, 96, 128)
    pred = render.permute(2, 0, 1)[None]
    with backend.torch_reference():
        dssim(pred.detach(), gt)  # the window and constants are built once
        with CountOps() as forward:
            loss = 0.8 * l1(pred, gt) + 0.2 * dssim(pred, gt)
        with CountOps() as backward:
            loss.backward()
    total = sum(forward.counts.values()) + sum(backward.counts.values())
    assert total <= 64, (dict(forward.counts), dict(backward.counts))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (the GPU campaign runs it)")
def test_stacked_dssim_on_cuda_equals_kornia():
    torch.manual_seed(5)
    gt = torch.rand(1, 3, 96, 128, device="cuda")
    pred = (gt + 0.2 * torch.randn_like(gt)).clamp(0, 1).requires_grad_(True)
    value = dssim(pred, gt)
    assert "Stacked" in type(value.grad_fn).__name__
    (grad,) = torch.autograd.grad(value, pred)
    reference = _kornia_dssim(pred, gt)
    (g_reference,) = torch.autograd.grad(reference, pred)
    np.testing.assert_allclose(float(value), float(reference), rtol=0, atol=1e-6)
    scale = float(g_reference.abs().max())
    np.testing.assert_allclose(grad.cpu().numpy(), g_reference.cpu().numpy(), rtol=0, atol=1e-4 * scale)
