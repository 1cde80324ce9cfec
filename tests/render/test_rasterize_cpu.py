"""The fast CPU rasterizer (numba) against the pure-torch reference and independent computations."""

import numpy as np
import pytest
import torch

from kc_splatfacto.render.constants import TILE_SIZE
from kc_splatfacto.render.rasterize_cpu import rasterize_to_pixels_cpu
from kc_splatfacto.render.rasterize_torch import rasterize_to_pixels_torch
from kc_splatfacto.render.tiles import isect_offset_encode, isect_tiles, tile_grid
from tests.render.cameras import turning_viewmats


def random_splats(n_cameras, n_gauss, width, height, channels, seed=0, sigma_px=(0.5, 4.0), margin=8.0,
                  tile_size=TILE_SIZE):
    """Random screen-space Gaussians with the benchmark's statistics, and their sorted tile intersections.

    Returns (means2d [C,N,2], conics [C,N,3], colors [C,N,D], opacities [C,N], isect_offsets, flatten_ids).
    """
    g = torch.Generator().manual_seed(seed)
    lo = torch.tensor([-margin, -margin])
    hi = torch.tensor([width + margin, height + margin])
    means2d = lo + torch.rand(n_cameras, n_gauss, 2, generator=g) * (hi - lo)
    sig = sigma_px[0] + (sigma_px[1] - sigma_px[0]) * torch.rand(n_cameras, n_gauss, 2, generator=g)
    rho = (torch.rand(n_cameras, n_gauss, generator=g) - 0.5) * 1.6
    sxx, syy, sxy = sig[..., 0] ** 2, sig[..., 1] ** 2, rho * sig[..., 0] * sig[..., 1]
    det = sxx * syy - sxy**2
    conics = torch.stack([syy / det, -sxy / det, sxx / det], dim=-1)
    colors = torch.rand(n_cameras, n_gauss, channels, generator=g)
    opacities = 0.05 + 0.9 * torch.rand(n_cameras, n_gauss, generator=g)
    depths = 1.0 + torch.rand(n_cameras, n_gauss, generator=g)
    radii = torch.ceil(3.0 * sig).to(torch.int32)
    return (means2d, conics, colors, opacities) + intersections(means2d, radii, depths, width, height, tile_size)


def intersections(means2d, radii, depths, width, height, tile_size=TILE_SIZE):
    tile_w, tile_h = tile_grid(width, height, tile_size)
    _, isect_ids, flatten_ids = isect_tiles(means2d, radii, depths, tile_size, tile_w, tile_h)
    return isect_offset_encode(isect_ids, means2d.shape[0], tile_w, tile_h), flatten_ids


def run_both(inputs, width, height, backgrounds=None, seed=1, absgrad=False, tile_size=TILE_SIZE):
    """Forward + backward of a random linear loss through both paths -> (outputs, grads) for each."""
    means2d, conics, colors, opacities, offsets, flatten_ids = inputs
    results = []
    weights = None
    for fn in (rasterize_to_pixels_cpu, rasterize_to_pixels_torch):
        leaves = [t.detach().clone().requires_grad_(True) for t in (means2d, conics, colors, opacities)]
        bg = None if backgrounds is None else backgrounds.detach().clone().requires_grad_(True)
        out_colors, out_alphas = fn(*leaves, width, height, tile_size, offsets, flatten_ids, backgrounds=bg,
                                    absgrad=absgrad)
        if weights is None:
            g = torch.Generator().manual_seed(seed)
            weights = (torch.randn(out_colors.shape, generator=g), torch.randn(out_alphas.shape, generator=g))
        ((out_colors * weights[0]).sum() + (out_alphas * weights[1]).sum()).backward()
        grads = [t.grad for t in leaves] + ([bg.grad] if bg is not None else [])
        results.append(((out_colors.detach(), out_alphas.detach()), grads, leaves[0]))
    return results


def assert_grad_close(actual, expected, name):
    # <= 1e-4 relative, plus an absolute floor scaled to the gradient's magnitude (float32 sums of ~1e3 terms)
    floor = 1e-5 * max(expected.abs().max().item(), 1e-3)
    torch.testing.assert_close(actual, expected, rtol=1e-4, atol=floor, msg=lambda m: f"{name}: {m}")


@pytest.mark.parametrize(
    "n_cameras, n_gauss, width, height, channels, with_bg, tile_size",
    [
        (1, 400, 48, 32, 3, False, 16),  # RGB, tile-aligned
        (2, 300, 45, 37, 4, True, 16),  # RGB+D, two cameras, backgrounds, partial edge tiles
        (1, 200, 23, 50, 1, True, 16),  # D only
        (2, 300, 45, 37, 4, True, 8),  # other tile sizes take the scalar kernels
    ],
)
def test_forward_and_gradients_match_reference(n_cameras, n_gauss, width, height, channels, with_bg, tile_size):
    inputs = random_splats(n_cameras, n_gauss, width, height, channels, seed=n_gauss, tile_size=tile_size)
    backgrounds = torch.rand(n_cameras, channels, generator=torch.Generator().manual_seed(7)) if with_bg else None
    (fast_out, fast_grads, _), (ref_out, ref_grads, _) = run_both(inputs, width, height, backgrounds,
                                                                  tile_size=tile_size)
    assert fast_out[0].shape == (n_cameras, height, width, channels)
    assert fast_out[1].shape == (n_cameras, height, width, 1)
    # the scene really covers the image and really saturates some pixels
    assert fast_out[1].mean() > 0.5
    torch.testing.assert_close(fast_out[0], ref_out[0], rtol=0, atol=1e-5)
    torch.testing.assert_close(fast_out[1], ref_out[1], rtol=0, atol=1e-5)
    names = ["means2d", "conics", "colors", "opacities", "backgrounds"]
    for name, actual, expected in zip(names, fast_grads, ref_grads):
        assert expected.abs().max() > 0, f"{name}: the reference gradient is zero, the test would be vacuous"
        assert_grad_close(actual, expected, name)


def test_saturated_pixels_stop_before_transmittance_threshold():
    """Hundreds of opaque Gaussians on one spot: compositing stops early, identically in both paths."""
    n = 300
    g = torch.Generator().manual_seed(3)
    means2d = (torch.tensor([20.3, 17.6]) + torch.randn(1, n, 2, generator=g)).float()
    conics = torch.tensor([0.08, 0.01, 0.06]).expand(1, n, 3).clone()
    colors = torch.rand(1, n, 3, generator=g)
    opacities = 0.5 + 0.5 * torch.rand(1, n, generator=g)
    opacities[0, :5] = 1.0  # clamped to ALPHA_CLAMP
    depths = torch.linspace(1.0, 2.0, n).reshape(1, n)
    radii = torch.full((1, n, 2), 12, dtype=torch.int32)
    inputs = (means2d, conics, colors, opacities) + intersections(means2d, radii, depths, 40, 36)
    (fast_out, fast_grads, _), (ref_out, ref_grads, _) = run_both(inputs, 40, 36)
    assert fast_out[1].max() > 1.0 - 2e-4  # some pixels reached the transmittance floor
    torch.testing.assert_close(fast_out[0], ref_out[0], rtol=0, atol=1e-5)
    torch.testing.assert_close(fast_out[1], ref_out[1], rtol=0, atol=1e-5)
    for name, actual, expected in zip(["means2d", "conics", "colors", "opacities"], fast_grads, ref_grads):
        assert_grad_close(actual, expected, name)


def test_indefinite_and_extreme_conics_are_tested_at_every_pixel():
    """A conic that is not positive definite has no bounded ellipse, and a nearly flat one has an extent beyond any
    integer (1e19 px): the fast path must cull neither's pixels."""
    means2d = torch.tensor([[[10.0, 9.0], [14.0, 12.0], [20.0, 6.0]]])
    # first: det < 0, sigma < 0 along a diagonal; third: a = 1e-38, a horizontal band across the whole image
    conics = torch.tensor([[[0.05, 0.2, 0.04], [0.3, 0.0, 0.2], [1e-38, 0.0, 0.5]]])
    colors = torch.tensor([[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]])
    opacities = torch.tensor([[0.9, 0.7, 0.8]])
    depths = torch.tensor([[1.0, 2.0, 3.0]])
    radii = torch.full((1, 3, 2), 40, dtype=torch.int32)
    inputs = (means2d, conics, colors, opacities) + intersections(means2d, radii, depths, 32, 24)
    (fast_out, fast_grads, _), (ref_out, ref_grads, _) = run_both(inputs, 32, 24)
    # the indefinite Gaussian contributes far from its centre where sigma is small and positive
    assert (fast_out[0][0, :, :, 0] > 0.01).sum() > 50
    assert (fast_out[0][0, 6, :, 2] > 0.1).all()  # the band reaches both image borders
    torch.testing.assert_close(fast_out[0], ref_out[0], rtol=0, atol=1e-5)
    for name, actual, expected in zip(["means2d", "conics", "colors", "opacities"], fast_grads, ref_grads):
        assert_grad_close(actual, expected, name)


def test_absgrad_equals_sum_of_per_pixel_absolute_gradients():
    """means2d.absgrad = sum over pixels of |d loss_pixel / d means2d|, from a per-pixel Jacobian of the reference."""
    width, height = 20, 18
    inputs = random_splats(1, 12, width, height, 3, seed=5, sigma_px=(1.5, 4.0), margin=0.0)
    means2d, conics, colors, opacities, offsets, flatten_ids = inputs
    g = torch.Generator().manual_seed(11)
    w_colors = torch.randn(1, height, width, 3, generator=g)
    w_alphas = torch.randn(1, height, width, 1, generator=g)

    leaf = means2d.clone().requires_grad_(True)
    out_colors, out_alphas = rasterize_to_pixels_cpu(leaf, conics, colors, opacities, width, height, TILE_SIZE,
                                                     offsets, flatten_ids, absgrad=True)
    ((out_colors * w_colors).sum() + (out_alphas * w_alphas).sum()).backward()

    def per_pixel_loss(m2d):
        c, a = rasterize_to_pixels_torch(m2d, conics, colors, opacities, width, height, TILE_SIZE, offsets,
                                         flatten_ids)
        return ((c * w_colors).sum(-1) + (a * w_alphas).sum(-1)).reshape(-1)  # [P]

    jac = torch.autograd.functional.jacobian(per_pixel_loss, means2d.clone())  # [P, 1, N, 2]
    expected = jac.abs().sum(dim=0)
    assert expected.abs().max() > 0
    torch.testing.assert_close(leaf.absgrad, expected, rtol=1e-4, atol=1e-5 * expected.abs().max().item())
    # and the signed sum of the same Jacobian is the ordinary gradient
    torch.testing.assert_close(leaf.grad, jac.sum(dim=0), rtol=1e-4, atol=1e-5 * expected.abs().max().item())


def test_backward_is_deterministic_across_thread_counts():
    import numba

    inputs = random_splats(1, 2000, 64, 64, 3, seed=2)
    grads = []
    previous = numba.get_num_threads()
    try:
        for threads in (1, numba.config.NUMBA_NUM_THREADS):
            numba.set_num_threads(threads)
            leaves = [t.clone().requires_grad_(True) for t in inputs[:4]]
            out_colors, out_alphas = rasterize_to_pixels_cpu(*leaves, 64, 64, TILE_SIZE, *inputs[4:])
            (out_colors.square().sum() + out_alphas.sum()).backward()
            grads.append([t.grad for t in leaves])
    finally:
        numba.set_num_threads(previous)
    for a, b in zip(*grads):
        assert torch.equal(a, b)


def test_no_intersections_gives_background_and_zero_gradients():
    means2d, conics, colors, opacities = (torch.zeros(1, 3, 2), torch.ones(1, 3, 3), torch.rand(1, 3, 3),
                                          torch.rand(1, 3))
    offsets = torch.zeros(1, 2, 3, dtype=torch.int32)
    flatten_ids = torch.zeros(0, dtype=torch.int32)
    bg = torch.tensor([[0.2, 0.4, 0.6]], requires_grad=True)
    leaves = [t.clone().requires_grad_(True) for t in (means2d, conics, colors, opacities)]
    out_colors, out_alphas = rasterize_to_pixels_cpu(*leaves, 40, 20, TILE_SIZE, offsets, flatten_ids,
                                                     backgrounds=bg)
    assert torch.equal(out_colors, bg.detach().expand(1, 20, 40, 3).reshape(1, 20, 40, 3))
    assert torch.equal(out_alphas, torch.zeros(1, 20, 40, 1))
    out_colors.sum().backward()
    assert all(torch.equal(t.grad, torch.zeros_like(t)) for t in leaves)
    torch.testing.assert_close(bg.grad, torch.full((1, 3), 800.0))


def test_one_pixel_image_matches_reference():
    inputs = random_splats(1, 30, 1, 1, 3, seed=4, sigma_px=(0.5, 2.0), margin=2.0)
    (fast_out, fast_grads, _), (ref_out, ref_grads, _) = run_both(inputs, 1, 1)
    assert fast_out[1].item() > 0
    torch.testing.assert_close(fast_out[0], ref_out[0], rtol=0, atol=1e-5)
    for name, actual, expected in zip(["means2d", "conics", "colors", "opacities"], fast_grads, ref_grads):
        assert_grad_close(actual, expected, name)


def test_float64_inputs_keep_their_dtype():
    inputs = random_splats(1, 100, 32, 32, 3, seed=8)
    leaves = [t.double().requires_grad_(True) for t in inputs[:4]]
    out_colors, out_alphas = rasterize_to_pixels_cpu(*leaves, 32, 32, TILE_SIZE, *inputs[4:])
    assert out_colors.dtype == torch.float64 and out_alphas.dtype == torch.float64
    out_colors.sum().backward()
    assert all(t.grad.dtype == torch.float64 for t in leaves)


@pytest.mark.parametrize(
    "bad, message",
    [
        (dict(conics=torch.zeros(1, 5, 2)), "conics must be"),
        (dict(opacities=torch.zeros(5)), "opacities must be"),
        (dict(isect_offsets=torch.zeros(1, 1, 1, dtype=torch.int32)), "isect_offsets must be"),
        (dict(backgrounds=torch.zeros(1, 4)), "backgrounds must be"),
    ],
)
def test_bad_shapes_are_clear_errors(bad, message):
    args = dict(means2d=torch.zeros(1, 5, 2), conics=torch.zeros(1, 5, 3), colors=torch.zeros(1, 5, 3),
                opacities=torch.zeros(1, 5), image_width=40, image_height=20, tile_size=TILE_SIZE,
                isect_offsets=torch.zeros(1, 2, 3, dtype=torch.int32), flatten_ids=torch.zeros(0, dtype=torch.int32),
                backgrounds=None)
    args.update(bad)
    with pytest.raises(ValueError, match=message):
        rasterize_to_pixels_cpu(**args)


def test_packed_extent_is_conservative_and_tight():
    """The packed ellipse extent bounds the pixels with alpha >= threshold: at the ellipse's extreme points just
    beyond it alpha is below the threshold (culling is exact), just inside it is above (culling saves work)."""
    from kc_splatfacto.render import _cpu_kernels as K
    from kc_splatfacto.render.constants import ALPHA_THRESHOLD

    n = 500
    inputs = random_splats(1, n, 64, 64, 3, seed=9)
    means2d, conics, colors = (t.reshape(n, -1) for t in inputs[:3])
    opacities = inputs[3].reshape(n)
    packed = np.empty((n, K.PACK_HEAD + 3), np.float32)
    K.pack_isects(means2d.numpy(), conics.numpy(), opacities.numpy(), colors.numpy(),
                  np.arange(n, dtype=np.int32), np.float32(ALPHA_THRESHOLD), packed)
    extent = torch.from_numpy(packed[:, 6:8].astype(np.float64))
    a, b, c = conics.double().unbind(-1)
    # the ellipse point of largest |dx| has b dx + c dy = 0; of largest |dy|, a dx + b dy = 0
    def alpha_at(dx, dy):
        return opacities.double() * torch.exp(-(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy))

    for scale, below in ((1.0001, True), (0.98, False)):
        ex, ey = extent[:, 0] * scale, extent[:, 1] * scale
        for alpha in (alpha_at(ex, -b / c * ex), alpha_at(-b / a * ey, ey)):
            if below:
                assert (alpha < ALPHA_THRESHOLD).all()
            else:
                assert (alpha > ALPHA_THRESHOLD).all()
    # the per-pixel pre-test: at sigma = sigma_cut the float32 alpha is below the threshold, a little inside above
    sigma_cut = torch.from_numpy(packed[:, 8].copy())
    assert (opacities * torch.exp(-sigma_cut) < ALPHA_THRESHOLD).all()
    assert (opacities * torch.exp(-(sigma_cut - 0.01)) > ALPHA_THRESHOLD).all()


def scene_3d(n, n_cameras, seed, sh_degree):
    """Gaussians in front of cameras that look down +z from slightly different places (float32)."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 0.6 + torch.tensor([0.0, 0.0, 3.0])
    quats = torch.randn(n, 4, generator=g)
    scales = 0.02 + 0.1 * torch.rand(n, 3, generator=g)
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    colors = (torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.4 if sh_degree is not None
              else torch.rand(n, 3, generator=g))
    viewmats = turning_viewmats(n_cameras, 0.12)
    return means, quats, scales, opacities, colors, viewmats


@pytest.mark.parametrize(
    "sh_degree, render_mode, rasterize_mode, with_bg",
    [(3, "RGB+ED", "classic", True), (None, "RGB", "antialiased", False), (None, "D", "classic", False)],
)
def test_rasterization_cpu_backend_matches_torch_backend(sh_degree, render_mode, rasterize_mode, with_bg):
    """The whole pipeline: outputs and gradients w.r.t. every Gaussian parameter and means2d."""
    from kc_splatfacto.render import rasterization

    width, height, n_cameras = 50, 38, 2
    params = scene_3d(250, n_cameras, seed=21, sh_degree=sh_degree)
    viewmats = params[5]
    Ks = torch.tensor([[60.0, 0, 25.3], [0, 62.0, 18.6], [0, 0, 1]]).repeat(n_cameras, 1, 1)
    backgrounds = torch.tensor([[0.1, 0.5, 0.9], [0.7, 0.2, 0.4]]) if with_bg else None
    results = {}
    for backend in ("cpu", "torch"):
        leaves = [t.clone().requires_grad_(True) for t in params[:5]]
        out_colors, out_alphas, meta = rasterization(
            *leaves, viewmats, Ks, width, height, sh_degree=sh_degree, backgrounds=backgrounds,
            render_mode=render_mode, rasterize_mode=rasterize_mode, absgrad=True, rasterizer=backend)
        g = torch.Generator().manual_seed(3)
        loss = ((out_colors * torch.randn(out_colors.shape, generator=g)).sum()
                + (out_alphas * torch.randn(out_alphas.shape, generator=g)).sum())
        loss.backward()
        results[backend] = (out_colors.detach(), out_alphas.detach(),
                            [t.grad for t in leaves] + [meta["means2d"].grad, meta["means2d"].absgrad])
    fast, ref = results["cpu"], results["torch"]
    assert fast[1].mean() > 0.3
    # depth channels are ~3 (world units): 1e-5 absolute on colour/alpha, relative on depth
    depth_scale = 3.0 if render_mode != "RGB" else 1.0
    torch.testing.assert_close(fast[0], ref[0], rtol=0, atol=1e-5 * depth_scale)
    torch.testing.assert_close(fast[1], ref[1], rtol=0, atol=1e-5)
    names = ["means", "quats", "scales", "opacities", "colors", "means2d", "means2d.absgrad"]
    for name, actual, expected in zip(names, fast[2], ref[2]):
        if name == "colors" and render_mode == "D":
            assert actual is None and expected is None  # depth-only renders never read the colours
            continue
        assert expected.abs().max() > 0, f"{name}: the reference gradient is zero, the test would be vacuous"
        assert_grad_close(actual, expected, name)


def test_branch_free_exp_is_within_two_ulp():
    from numba import njit

    from kc_splatfacto.render import _cpu_kernels as K

    @njit
    def exp_neg_array(s, out):
        for i in range(s.shape[0]):
            out[i] = K.exp_neg(s[i])

    s = np.linspace(0.0, 12.0, 200_001, dtype=np.float32)
    out = np.empty_like(s)
    exp_neg_array(s, out)
    exact = np.exp(-s.astype(np.float64))
    assert np.max(np.abs(out - exact) / exact) < 2.0 * 2.0**-23
