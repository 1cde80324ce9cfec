"""The torch reference rasterizer against independent oracles: a dense per-pixel brute-force loop written here in
numpy float64 (no tiles), gradcheck (finite differences), per-pixel autograd for absgrad, and the render-mode
identities of gsplat's rasterization()."""

import math

import numpy as np
import pytest
import torch

from kc_splatfacto.render import fully_fused_projection, rasterization, rasterize_to_pixels_torch
from kc_splatfacto.render.tiles import isect_offset_encode, isect_tiles, tile_grid


def random_scene(n, seed=0, dtype=torch.float64, n_cameras=2, spread=0.6, scale=(0.02, 0.12)):
    """Gaussians in front of cameras looking down +z from slightly different places."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * spread + torch.tensor([0.0, 0.0, 3.0], dtype=dtype)
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.empty(n, 3, dtype=dtype).uniform_(*scale, generator=g)
    opacities = torch.empty(n, dtype=dtype).uniform_(0.05, 0.95, generator=g)
    colors = torch.rand(n, 3, generator=g, dtype=dtype)
    viewmats = torch.eye(4, dtype=dtype).repeat(n_cameras, 1, 1)
    for c in range(n_cameras):
        angle = 0.1 * c
        viewmats[c, :3, :3] = torch.tensor(
            [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]], dtype=dtype
        )
        viewmats[c, :3, 3] = torch.tensor([0.1 * c, -0.05 * c, 0.2 * c], dtype=dtype)
    return means, quats, scales, opacities, colors, viewmats


def intrinsics(width, height, focal, n_cameras, dtype=torch.float64):
    K = torch.tensor([[focal, 0, width / 2.0 + 0.3], [0, focal * 1.05, height / 2.0 - 0.7], [0, 0, 1]], dtype=dtype)
    return K.repeat(n_cameras, 1, 1)


def dense_bruteforce(means2d, conics, colors, opacities, radii, depths, width, height, backgrounds=None):
    """gsplat's per-pixel loop, written independently: every visible Gaussian of the camera, sorted by depth
    (ties by index), no tiles. float64 numpy."""
    means2d, conics, colors, opacities, depths = (
        t.detach().double().numpy() for t in (means2d, conics, colors, opacities, depths)
    )
    radii = radii.numpy()
    n_cameras, _, channels = colors.shape
    out = np.zeros((n_cameras, height, width, channels))
    out_alpha = np.zeros((n_cameras, height, width, 1))
    for c in range(n_cameras):
        visible = np.nonzero((radii[c] > 0).all(-1))[0]
        order = visible[np.lexsort((visible, depths[c, visible].astype(np.float32)))]
        for i in range(height):
            for j in range(width):
                px, py = j + 0.5, i + 0.5
                T, acc = 1.0, np.zeros(channels)
                for g in order:
                    dx, dy = means2d[c, g, 0] - px, means2d[c, g, 1] - py
                    a, b, cc = conics[c, g]
                    sigma = 0.5 * (a * dx * dx + cc * dy * dy) + b * dx * dy
                    alpha = min(0.999, opacities[c, g] * math.exp(-sigma))
                    if sigma < 0 or alpha < 1.0 / 255.0:
                        continue
                    if T * (1 - alpha) <= 1e-4:
                        break
                    acc += colors[c, g] * alpha * T
                    T *= 1 - alpha
                out[c, i, j] = acc + (0 if backgrounds is None else T * backgrounds[c].double().numpy())
                out_alpha[c, i, j, 0] = 1 - T
    return out, out_alpha


def project_and_bin(means, quats, scales, opacities, viewmats, Ks, width, height, tile_size=16):
    proj = fully_fused_projection(means, quats, scales, viewmats, Ks, width, height, opacities=opacities)
    tile_width, tile_height = tile_grid(width, height, tile_size)
    _, isect_ids, flatten_ids = isect_tiles(proj.means2d, proj.radii, proj.depths, tile_size, tile_width, tile_height)
    offsets = isect_offset_encode(isect_ids, viewmats.shape[0], tile_width, tile_height)
    return proj, offsets, flatten_ids


@pytest.mark.parametrize("tile_size", [16, 8])
def test_tiled_reference_equals_dense_bruteforce(tile_size):
    width, height = 37, 29  # not multiples of the tile size: partial tiles on both edges
    means, quats, scales, opacities, colors, viewmats = random_scene(60, seed=1)
    Ks = intrinsics(width, height, 30.0, 2)
    proj, offsets, flatten_ids = project_and_bin(means, quats, scales, opacities, viewmats, Ks, width, height, tile_size)
    assert (proj.radii > 0).all(-1).sum() > 40, "scene should be mostly visible"
    colors_c = colors[None].expand(2, -1, -1)
    opac_c = opacities[None].expand(2, -1)
    bg = torch.tensor([[0.2, 0.3, 0.4], [1.0, 0.0, 0.5]], dtype=torch.float64)
    render, alpha = rasterize_to_pixels_torch(
        proj.means2d, proj.conics, colors_c, opac_c, width, height, tile_size, offsets, flatten_ids, backgrounds=bg
    )
    expected, expected_alpha = dense_bruteforce(
        proj.means2d, proj.conics, colors_c, opac_c, proj.radii, proj.depths, width, height, bg
    )
    assert render.shape == (2, height, width, 3) and alpha.shape == (2, height, width, 1)
    np.testing.assert_allclose(render.detach().numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(alpha.detach().numpy(), expected_alpha, atol=1e-12)
    assert expected_alpha.max() > 0.9 and expected_alpha.min() < 0.1  # the comparison covers real coverage


def test_transmittance_stop_and_alpha_clamp_match_bruteforce():
    """Many nearly opaque Gaussians on the same pixels: compositing must stop before T drops to 1e-4."""
    width, height = 8, 8
    n = 12
    means = torch.tensor([[0.0, 0.0, 2.0 + 0.1 * k] for k in range(n)], dtype=torch.float64)
    quats = torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64).repeat(n, 1)
    scales = torch.full((n, 3), 0.3, dtype=torch.float64)
    opacities = torch.tensor([1.0, 0.7, 0.9, 0.5, 0.99, 0.6, 0.95, 0.8, 0.9, 0.85, 0.75, 1.0], dtype=torch.float64)
    colors = torch.rand(n, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    viewmats = torch.eye(4, dtype=torch.float64)[None]
    Ks = intrinsics(width, height, 10.0, 1)
    proj, offsets, flatten_ids = project_and_bin(means, quats, scales, opacities, viewmats, Ks, width, height)
    render, alpha = rasterize_to_pixels_torch(
        proj.means2d, proj.conics, colors[None], opacities[None], width, height, 16, offsets, flatten_ids
    )
    expected, expected_alpha = dense_bruteforce(
        proj.means2d, proj.conics, colors[None], opacities[None], proj.radii, proj.depths, width, height
    )
    np.testing.assert_allclose(render.detach().numpy(), expected, atol=1e-12)
    np.testing.assert_allclose(alpha.detach().numpy(), expected_alpha, atol=1e-12)
    # the stop rule really fired: T stayed above 1e-4 although the product of all (1 - alpha) is far below it
    assert (1 - alpha.max()) > 1e-4
    assert alpha.max() > 0.999


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_gradcheck_reference_tiny_scene(rasterize_mode):
    """Autograd of the whole reference pipeline (projection, SH, tiles, compositing) against finite differences."""
    width, height = 8, 6
    means, quats, scales, opacities, _, viewmats = random_scene(3, seed=5, n_cameras=2, spread=0.3, scale=(0.1, 0.3))
    opacities = opacities.clamp(0.1, 0.8)
    sh = torch.randn(3, 4, 3, generator=torch.Generator().manual_seed(6), dtype=torch.float64) * 0.3
    Ks = intrinsics(width, height, 8.0, 2)
    bg = torch.tensor([[0.1, 0.2, 0.3], [0.3, 0.2, 0.1]], dtype=torch.float64)

    def render(means, quats, scales, opacities, sh):
        colors, alphas, _ = rasterization(
            means, quats, scales, opacities, sh, viewmats, Ks, width, height, sh_degree=1, backgrounds=bg,
            tile_size=4, render_mode="RGB+ED", rasterize_mode=rasterize_mode, rasterizer="torch",
        )
        return colors, alphas

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, sh))
    assert render(*inputs)[1].max() > 0.3
    # fast_mode: finite differences along random directions (v^T J u) instead of the full Jacobian, which would cost a
    # backward pass (each re-running the checkpointed tiles) per output pixel
    assert torch.autograd.gradcheck(render, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_gradcheck_rasterize_stage_inputs():
    """Gradients with respect to the stage inputs (means2d, conics, colors, opacities, backgrounds)."""
    width, height = 9, 6
    means, quats, scales, opacities, colors, viewmats = random_scene(5, seed=7, n_cameras=1, spread=0.3, scale=(0.1, 0.3))
    Ks = intrinsics(width, height, 8.0, 1)
    proj, offsets, flatten_ids = project_and_bin(
        means, quats, scales, opacities.clamp(max=0.8), viewmats, Ks, width, height, tile_size=4
    )

    def stage(means2d, conics, colors, opacities, bg):
        return rasterize_to_pixels_torch(means2d, conics, colors, opacities, width, height, 4, offsets, flatten_ids, bg)

    inputs = (
        proj.means2d.detach().clone().requires_grad_(True),
        proj.conics.detach().clone().requires_grad_(True),
        colors[None].clone().requires_grad_(True),
        opacities.clamp(max=0.8)[None].clone().requires_grad_(True),
        torch.tensor([[0.5, 0.1, 0.9]], dtype=torch.float64, requires_grad=True),
    )
    assert torch.autograd.gradcheck(stage, inputs, eps=1e-6, atol=1e-7, rtol=1e-5)


def test_means2d_grad_and_absgrad_against_per_pixel_autograd():
    width, height = 7, 5
    means, quats, scales, opacities, colors, viewmats = random_scene(6, seed=11, n_cameras=1, spread=0.25)
    means.requires_grad_(True)
    Ks = intrinsics(width, height, 9.0, 1)
    weights = torch.randn(1, height, width, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    out, _, meta = rasterization(
        means, quats, scales, opacities, colors, viewmats, Ks, width, height, absgrad=True, rasterizer="torch"
    )
    means2d = meta["means2d"]
    (out * weights).sum().backward()
    # oracle: the gradient of each pixel's loss separately, through a fresh render (same inputs, no hooks)
    per_pixel_abs = torch.zeros_like(means2d)
    total = torch.zeros_like(means2d)
    for i in range(height):
        for j in range(width):
            out2, _, meta2 = rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, rasterizer="torch")
            (grad,) = torch.autograd.grad((out2[0, i, j] * weights[0, i, j]).sum(), meta2["means2d"], allow_unused=True)
            if grad is not None:
                per_pixel_abs += grad.abs()
                total += grad
    assert means2d.grad is not None and means2d.grad.abs().sum() > 0
    torch.testing.assert_close(means2d.grad, total, atol=1e-12, rtol=1e-10)
    torch.testing.assert_close(means2d.absgrad, per_pixel_abs, atol=1e-12, rtol=1e-10)
    assert (means2d.absgrad >= means2d.grad.abs() - 1e-12).all()
    assert (means2d.absgrad > means2d.grad.abs() + 1e-9).any()  # signs really cancel somewhere


def _scene_for_modes():
    width, height = 20, 14
    means, quats, scales, opacities, colors, viewmats = random_scene(30, seed=4, n_cameras=2)
    Ks = intrinsics(width, height, 16.0, 2)
    return (means, quats, scales, opacities, colors, viewmats, Ks, width, height)


def test_render_modes_follow_gsplat_definitions():
    args = _scene_for_modes()
    means = args[0]
    rgb, alpha, meta = rasterization(*args, rasterizer="torch")
    depth, alpha_d, _ = rasterization(*args, render_mode="D", rasterizer="torch")
    exp_depth, _, _ = rasterization(*args, render_mode="ED", rasterizer="torch")
    rgbd, _, _ = rasterization(*args, render_mode="RGB+D", rasterizer="torch")
    rgbed, _, _ = rasterization(*args, render_mode="RGB+ED", rasterizer="torch")
    # accumulated depth = the RGB compositing of per-Gaussian camera z as a colour
    viewmats = args[5]
    z = (torch.einsum("cij,nj->cni", viewmats[:, :3, :3], means) + viewmats[:, None, :3, 3])[..., 2]
    as_color, _, _ = rasterization(*args[:4], z[..., None], *args[5:], rasterizer="torch")
    torch.testing.assert_close(depth, as_color, atol=1e-12, rtol=0)
    torch.testing.assert_close(alpha_d, alpha)
    torch.testing.assert_close(exp_depth, depth / alpha.clamp(min=1e-10))
    torch.testing.assert_close(rgbd, torch.cat([rgb, depth], -1))
    torch.testing.assert_close(rgbed, torch.cat([rgb, exp_depth], -1))
    assert depth.shape[-1] == 1 and rgbd.shape[-1] == 4
    assert meta["n_cameras"] == 2 and meta["width"] == 20 and meta["height"] == 14
    assert meta["radii"].shape == (2, 30, 2) and meta["radii"].dtype == torch.int32


def test_backgrounds_blend_with_transmittance_and_depth_channel_gets_zero():
    args = _scene_for_modes()
    bg = torch.tensor([[0.9, 0.1, 0.4], [0.0, 1.0, 0.2]], dtype=torch.float64)
    plain, alpha, _ = rasterization(*args, rasterizer="torch")
    with_bg, _, _ = rasterization(*args, backgrounds=bg, rasterizer="torch")
    torch.testing.assert_close(with_bg, plain + (1 - alpha) * bg[:, None, None, :])
    rgbd_bg, _, _ = rasterization(*args, backgrounds=bg, render_mode="RGB+D", rasterizer="torch")
    depth, _, _ = rasterization(*args, render_mode="D", rasterizer="torch")
    torch.testing.assert_close(rgbd_bg[..., 3:], depth)


def test_sh_colors_and_per_camera_colors():
    args = list(_scene_for_modes())
    n = args[0].shape[0]
    sh0 = torch.randn(n, 1, 3, generator=torch.Generator().manual_seed(9), dtype=torch.float64)
    from_sh, _, _ = rasterization(*args[:4], sh0, *args[5:], sh_degree=0, rasterizer="torch")
    direct, _, _ = rasterization(*args[:4], torch.clamp_min(0.28209479177387814 * sh0[:, 0] + 0.5, 0), *args[5:], rasterizer="torch")
    torch.testing.assert_close(from_sh, direct)
    per_camera = torch.stack([args[4], 1 - args[4]])  # [C, N, 3]
    both, _, _ = rasterization(*args[:4], per_camera, *args[5:], rasterizer="torch")
    first, _, _ = rasterization(*args, rasterizer="torch")
    second, _, _ = rasterization(*args[:4], 1 - args[4], *args[5:], rasterizer="torch")
    torch.testing.assert_close(both, torch.stack([first[0], second[1]]))


def test_antialiased_scales_opacity_by_compensation():
    args = _scene_for_modes()
    _, _, meta_c = rasterization(*args, rasterizer="torch")
    _, _, meta_a = rasterization(*args, rasterize_mode="antialiased", rasterizer="torch")
    visible = (meta_a["radii"] > 0).all(-1)
    ratio = meta_a["opacities"][visible] / meta_c["opacities"][visible]
    assert (ratio < 1).all() and (ratio > 0).all()
    # compensation = sqrt(det(cov2d) / det(cov2d + 0.3 I)) with cov2d recovered from the classic conic
    a, b, c = meta_c["conics"][visible].unbind(-1)
    det_inv = a * c - b * b
    cov_xx, cov_xy, cov_yy = c / det_inv - 0.3, -b / det_inv, a / det_inv - 0.3
    expected = torch.sqrt((cov_xx * cov_yy - cov_xy**2) / ((cov_xx + 0.3) * (cov_yy + 0.3) - cov_xy**2))
    torch.testing.assert_close(ratio, expected)


def test_auto_backend_picks_cpu_for_cpu_tensors():
    from kc_splatfacto.render import resolve_rasterizer

    assert resolve_rasterizer("auto", torch.device("cpu")) == "cpu"
    args = _scene_for_modes()
    auto, auto_a, meta = rasterization(*[a.float() if torch.is_tensor(a) else a for a in args])
    ref, ref_a, _ = rasterization(*[a.float() if torch.is_tensor(a) else a for a in args], rasterizer="torch")
    assert meta["rasterizer"] == "cpu"
    torch.testing.assert_close(auto, ref, atol=1e-5, rtol=0)
    torch.testing.assert_close(auto_a, ref_a, atol=1e-5, rtol=0)


def test_backend_resolution_with_and_without_gsplat(monkeypatch):
    import sys
    import types

    from kc_splatfacto.render import resolve_rasterizer

    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    monkeypatch.setitem(sys.modules, "gsplat", types.ModuleType("gsplat"))  # an importable gsplat
    assert resolve_rasterizer("auto", cuda) == "gsplat"
    assert resolve_rasterizer("gsplat", cuda) == "gsplat"
    assert resolve_rasterizer("auto", cpu) == "cpu"
    with pytest.raises(RuntimeError, match="needs CUDA tensors"):
        resolve_rasterizer("gsplat", cpu)
    with pytest.raises(ValueError, match="needs CPU tensors"):
        resolve_rasterizer("cpu", cuda)
    monkeypatch.setitem(sys.modules, "gsplat", None)  # import gsplat now raises ImportError
    with pytest.raises(RuntimeError, match="pip install gsplat"):
        resolve_rasterizer("gsplat", cuda)
    with pytest.raises(RuntimeError, match="gsplat is not installed"):
        resolve_rasterizer("auto", cuda)
    assert resolve_rasterizer("auto", cpu) == "cpu"


def test_rasterizer_errors_are_clear():
    args = _scene_for_modes()
    with pytest.raises(ValueError, match="rasterizer must be one of"):
        rasterization(*args, rasterizer="opengl")
    gsplat_installed = True
    try:
        import gsplat  # noqa: F401
    except Exception:
        gsplat_installed = False
    with pytest.raises(RuntimeError, match="gsplat"):
        rasterization(*args, rasterizer="gsplat")  # CPU tensors: an error either way, never a silent fallback
    if not gsplat_installed:
        with pytest.raises(RuntimeError, match="pip install gsplat"):
            rasterization(*args, rasterizer="gsplat")
    with pytest.raises(ValueError, match="render_mode"):
        rasterization(*args, render_mode="RGBD", rasterizer="torch")
    with pytest.raises(ValueError, match="opacities must be"):
        rasterization(*args[:3], args[3][:, None], *args[4:], rasterizer="torch")


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_split_sh_colors_render_and_differentiate_as_one_tensor(backend):
    """rasterization(colors=SplitSH(dc, rest)) is rasterization(colors=cat([dc, rest])): the cpu backend reads the two
    tensors in place, the torch reference concatenates them; images and SH gradients are equal bit for bit."""
    from kc_splatfacto.render import SplitSH

    args = list(_scene_for_modes())
    n = args[0].shape[0]
    shs = torch.randn(n, 16, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64) * 0.3
    results = []
    for split in (False, True):
        dc = shs[:, :1].clone().requires_grad_(True)
        rest = shs[:, 1:].clone().requires_grad_(True)
        colors = SplitSH(dc, rest) if split else torch.cat([dc, rest], dim=1)
        image, _, _ = rasterization(*args[:4], colors, *args[5:], sh_degree=3, rasterizer=backend)
        (image * torch.linspace(-1, 1, image.numel(), dtype=image.dtype).reshape(image.shape)).sum().backward()
        results.append((image.detach(), dc.grad, rest.grad))
    for a, b in zip(*results):
        assert torch.equal(a, b)
    assert results[0][2].abs().max() > 0


@pytest.mark.parametrize("backend", ["torch", "cpu"])
def test_split_sh_colors_without_sh_degree_is_a_clear_error(backend):
    from kc_splatfacto.render import SplitSH

    args = list(_scene_for_modes())
    n = args[0].shape[0]
    shs = torch.zeros(n, 4, 3, dtype=args[0].dtype)
    with pytest.raises(ValueError, match="pass sh_degree"):
        rasterization(*args[:4], SplitSH(shs[:, :1], shs[:, 1:]), *args[5:], rasterizer=backend)
