"""Extreme inputs, each a test, on every CPU backend: outputs and gradients finite, and the value right where an
independent expectation exists (closed-form compositing, a cropped larger render, the background)."""

import math

import pytest
import torch

from kc_splatfacto.render import rasterization

BACKENDS = ["torch", "cpu"]
F32 = torch.float32


def camera(width, height, focal=None):
    focal = focal if focal is not None else 0.8 * max(width, height)
    Ks = torch.tensor([[[focal, 0, width / 2.0], [0, focal, height / 2.0], [0, 0, 1]]], dtype=F32)
    return torch.eye(4, dtype=F32)[None], Ks


def gaussians(means, scale=0.05, opacity=0.8, quats=None, colors=None):
    n = means.shape[0]
    params = {
        "means": means.to(F32),
        "quats": quats if quats is not None else torch.tensor([[1.0, 0.2, -0.1, 0.3]]).repeat(n, 1),
        "scales": torch.full((n, 3), scale, dtype=F32) if not torch.is_tensor(scale) else scale.to(F32),
        "opacities": torch.full((n,), opacity, dtype=F32) if not torch.is_tensor(opacity) else opacity.to(F32),
        "colors": colors if colors is not None else torch.rand(n, 3, generator=torch.Generator().manual_seed(n)),
    }
    return {k: v.clone().requires_grad_(True) for k, v in params.items()}


def render_and_backward(params, width, height, backend, bg=None, **kwargs):
    """Render, back-propagate a loss touching colours and alphas, return outputs, meta and input gradients."""
    viewmats, Ks = camera(width, height, kwargs.pop("focal", None))
    colors, alphas, meta = rasterization(
        params["means"], params["quats"], params["scales"], params["opacities"], params["colors"], viewmats, Ks,
        width, height, backgrounds=bg, rasterizer=backend, render_mode="RGB+ED", **kwargs,
    )
    weights = torch.linspace(-1, 1, colors.numel()).reshape(colors.shape)
    loss = (colors * weights).sum() + alphas.sum()
    if loss.requires_grad:
        loss.backward()
    grads = {k: v.grad for k, v in params.items()}
    return colors, alphas, meta, grads


def assert_finite(colors, alphas, grads):
    assert torch.isfinite(colors).all() and torch.isfinite(alphas).all()
    for name, g in grads.items():
        assert g is None or torch.isfinite(g).all(), f"non-finite gradient for {name}"


@pytest.mark.parametrize("backend", BACKENDS)
def test_no_gaussians(backend):
    params = gaussians(torch.zeros(0, 3))
    bg = torch.tensor([[0.2, 0.4, 0.6]], requires_grad=True)
    colors, alphas, meta, grads = render_and_backward(params, 20, 12, backend, bg=bg)
    assert colors.shape == (1, 12, 20, 4) and alphas.shape == (1, 12, 20, 1)
    assert (alphas == 0).all()
    torch.testing.assert_close(colors[..., :3], bg.detach().expand(1, 12, 20, 3).reshape(1, 12, 20, 3))
    assert (colors[..., 3] == 0).all()
    assert meta["radii"].shape == (1, 0, 2) and meta["isect_ids"].numel() == 0
    assert_finite(colors, alphas, grads)
    assert bg.grad is not None and torch.isfinite(bg.grad).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_every_gaussian_behind_the_camera(backend):
    means = torch.randn(50, 3, generator=torch.Generator().manual_seed(0))
    means[:, 2] = -means[:, 2].abs() - 0.5
    params = gaussians(means, scale=0.3)
    colors, alphas, meta, grads = render_and_backward(params, 24, 16, backend)
    assert (meta["radii"] == 0).all() and (alphas == 0).all() and (colors == 0).all()
    assert_finite(colors, alphas, grads)
    for name in ("means", "scales", "opacities", "colors"):
        assert grads[name] is None or (grads[name] == 0).all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_gaussian_straddling_the_near_plane(backend):
    # a large Gaussian whose centre is just past the near plane (its body extends behind the camera), one whose
    # centre is just before it (culled), and a normal one
    means = torch.tensor([[0.0, 0.0, 0.011], [0.01, 0.0, 0.009], [0.1, 0.05, 2.0]])
    params = gaussians(means, scale=torch.tensor([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0.1, 0.1, 0.1]]))
    colors, alphas, meta, grads = render_and_backward(params, 32, 24, backend)
    assert meta["radii"][0, 1].tolist() == [0, 0]
    assert (meta["radii"][0, 0] > 0).all() and (meta["radii"][0, 2] > 0).all()
    assert alphas.max() > 0.5
    assert_finite(colors, alphas, grads)
    assert grads["means"][0].abs().sum() > 0


@pytest.mark.parametrize("backend", BACKENDS)
def test_tiny_scale(backend):
    params = gaussians(torch.tensor([[0.0, 0.0, 2.0], [0.3, -0.2, 3.0]]), scale=1e-8, opacity=0.9)
    colors, alphas, meta, grads = render_and_backward(params, 32, 32, backend)
    # the eps2d dilation alone keeps a visible 0.3-px^2 footprint: alpha at the nearest pixel centre to the mean
    assert (meta["radii"] > 0).all()
    assert alphas.max() > 0.1
    assert_finite(colors, alphas, grads)


@pytest.mark.parametrize("backend", BACKENDS)
def test_huge_scale_covers_every_tile(backend):
    params = gaussians(torch.tensor([[0.0, 0.0, 5.0]]), scale=1e4, opacity=0.6)
    width, height = 50, 40
    colors, alphas, meta, grads = render_and_backward(params, width, height, backend)
    n_tiles = meta["tile_width"] * meta["tile_height"]
    assert int(meta["tiles_per_gauss"].sum()) == n_tiles == 12
    # flat at pixel scale: every pixel gets alpha = opacity
    torch.testing.assert_close(alphas, torch.full_like(alphas, 0.6), atol=1e-5, rtol=0)
    assert_finite(colors, alphas, grads)


@pytest.mark.parametrize("backend", BACKENDS)
def test_zero_norm_quaternion_renders_like_identity(backend):
    means = torch.tensor([[0.0, 0.0, 2.0], [0.2, 0.1, 2.5]])
    zero_q = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    ident_q = torch.tensor([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    scales = torch.tensor([[0.2, 0.05, 0.1], [0.1, 0.1, 0.1]])
    p_zero = gaussians(means, scale=scales, quats=zero_q)
    colors, alphas, _, grads = render_and_backward(p_zero, 32, 32, backend)
    assert_finite(colors, alphas, grads)
    p_ident = gaussians(means, scale=scales, quats=ident_q)
    colors_i, alphas_i, _, _ = render_and_backward(p_ident, 32, 32, backend)
    torch.testing.assert_close(colors, colors_i)
    torch.testing.assert_close(alphas, alphas_i)


@pytest.mark.parametrize("backend", BACKENDS)
def test_opacity_exactly_zero_and_one(backend):
    # focal 20, principal point (8, 8): x = 0.5 * z / 20 projects onto the pixel centre (8.5, 8.5), where sigma = 0
    means = torch.tensor([[0.0, 0.0, 2.0], [0.075, 0.075, 3.0]])
    params = gaussians(means, scale=0.2, opacity=torch.tensor([0.0, 1.0]))
    colors, alphas, meta, grads = render_and_backward(params, 16, 16, backend, focal=20.0)
    assert meta["radii"][0, 0].tolist() == [0, 0]  # opacity 0 < 1/255: culled
    assert (meta["radii"][0, 1] > 0).all()
    # at the centre the opaque Gaussian's alpha is clamped to 0.999
    assert alphas.max().item() == pytest.approx(0.999, abs=1e-6)
    assert_finite(colors, alphas, grads)


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_by_one_image(backend):
    params = gaussians(torch.tensor([[0.0, 0.0, 2.0], [0.05, 0.0, 2.5], [5.0, 0.0, 2.0]]), scale=0.1)
    colors, alphas, meta, grads = render_and_backward(params, 1, 1, backend, focal=4.0)
    assert colors.shape == (1, 1, 1, 4) and 0 < alphas.item() < 1
    assert meta["radii"][0, 2].tolist() == [0, 0]  # off-screen
    assert_finite(colors, alphas, grads)


@pytest.mark.parametrize("backend", BACKENDS)
def test_size_not_multiple_of_tile_equals_crop_of_larger_render(backend):
    g = torch.Generator().manual_seed(5)
    pixels = torch.rand(80, 2, generator=g) * torch.tensor([32.0, 16.0]) + 0.5  # inside the small image
    depth = torch.rand(80, 1, generator=g) + 2.0
    means = torch.cat([(pixels - torch.tensor([16.0, 8.0])) * depth / 30.0, depth], dim=-1)
    small_w, small_h, big_w, big_h = 33, 17, 48, 32
    focal = 30.0
    Ks_small = torch.tensor([[[focal, 0, 16.0], [0, focal, 8.0], [0, 0, 1]]])
    Ks_big = Ks_small.clone()
    # The same principal point in both: the big image is the small one plus extra columns/rows right and below.
    # Means stay inside the small frustum, so the FOV clamp of the Jacobian (which depends on the size) never acts.
    params = gaussians(means, scale=0.08)
    viewmats = torch.eye(4)[None]
    args = [params[k] for k in ("means", "quats", "scales", "opacities", "colors")]
    small, small_a, _ = rasterization(*args, viewmats, Ks_small, small_w, small_h, rasterizer=backend)
    big, big_a, _ = rasterization(*args, viewmats, Ks_big, big_w, big_h, rasterizer=backend)
    assert small.shape == (1, small_h, small_w, 3)
    torch.testing.assert_close(small, big[:, :small_h, :small_w], atol=1e-6, rtol=0)
    torch.testing.assert_close(small_a, big_a[:, :small_h, :small_w], atol=1e-6, rtol=0)
    assert small_a.mean() > 0.3
    (small.sum() + small_a.sum()).backward()
    assert_finite(small, small_a, {k: v.grad for k, v in params.items()})


@pytest.mark.parametrize("backend", BACKENDS)
def test_ten_thousand_gaussians_stacked_on_one_pixel(backend):
    n = 10_000
    means = torch.tensor([[0.0, 0.0, 2.0]]).repeat(n, 1)  # equal depths: composited in index order
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(1))
    params = gaussians(means, scale=0.01, opacity=0.3, quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), colors=colors)
    width = height = 16
    out, alphas, meta, grads = render_and_backward(params, width, height, backend, focal=100.0)
    assert_finite(out, alphas, grads)
    # closed form at the pixel nearest the mean (8, 8) -> centre (8.5, 8.5): identical alphas a; the loop stops at the
    # first k whose T would reach 1e-4, so k_max composited Gaussians with (1-a)^(k_max+1) <= 1e-4 < (1-a)^k_max
    conic = meta["conics"][0, 0]
    d = 0.5 - 0.0  # mean projects to the image centre (8, 8): offset 0.5 px on both axes
    sigma = 0.5 * (conic[0] * d * d + conic[2] * d * d) + conic[1] * d * d
    a = float(0.3 * torch.exp(-sigma.detach()))
    k_max = next(k for k in range(1, 100) if (1 - a) ** (k + 1) <= 1e-4)
    weights = torch.tensor([a * (1 - a) ** k for k in range(k_max)], dtype=torch.float64)
    expected = (weights[:, None] * colors[:k_max].double()).sum(0)
    torch.testing.assert_close(out[0, 8, 8, :3].double(), expected, atol=2e-5, rtol=0)
    assert alphas[0, 8, 8, 0].item() == pytest.approx(1 - (1 - a) ** k_max, abs=2e-5)
    # even the faintest pixel stops within ~2400 Gaussians (alpha >= 1/255): the rest get no gradient
    assert (grads["colors"][5000:] == 0).all() and (grads["colors"][:k_max] != 0).any()


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("field", ["means", "quats", "scales", "opacities", "colors"])
def test_nan_input_is_a_clear_error(backend, field):
    params = gaussians(torch.tensor([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0]]))
    bad = params[field].detach().clone()
    bad.view(-1)[0] = math.nan
    params[field] = bad
    viewmats, Ks = camera(8, 8)
    with pytest.raises(ValueError, match=f"{field} holds 1 NaN"):
        rasterization(params["means"], params["quats"], params["scales"], params["opacities"], params["colors"],
                      viewmats, Ks, 8, 8, rasterizer=backend)
