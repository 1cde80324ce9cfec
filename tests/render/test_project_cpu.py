"""The compiled projection + SH pass (``project_cpu``) against the torch reference (``fully_fused_projection`` then
``sh_to_rgb``), which autograd differentiates: forward values, every gradient, float64 gradcheck, thread counts."""

import math

import numba
import pytest
import torch

from kc_splatfacto.render.project_cpu import project_and_shade_cpu
from kc_splatfacto.render.projection import fully_fused_projection
from kc_splatfacto.render.sh import sh_to_rgb
from tests.render.cameras import turning_viewmats

WIDTH, HEIGHT = 64, 48


def scene(n=300, n_cameras=2, sh_degree=3, seed=0, dtype=torch.float64):
    """Gaussians around z = 3 seen by cameras that look down +z; some behind, some off-screen, some faint."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([1.2, 1.0, 1.0]) + torch.tensor([0.0, 0.0, 3.0])
    means[: n // 20, 2] = -1.0  # behind every camera
    quats = torch.randn(n, 4, generator=g)
    scales = 0.02 + 0.15 * torch.rand(n, 3, generator=g)
    opacities = torch.rand(n, generator=g)
    opacities[: n // 10] *= 0.01  # some below 1/255 (culled), some just above
    k = 16
    shs = torch.randn(n, k, 3, generator=g) * 0.5
    viewmats = turning_viewmats(n_cameras, 0.15)
    Ks = torch.tensor([[50.0, 0, 31.7], [0, 52.0, 23.2], [0, 0, 1]]).repeat(n_cameras, 1, 1)
    return [t.to(dtype) for t in (means, quats, scales, opacities, shs, viewmats, Ks)]


def reference(means, quats, scales, opacities, shs, viewmats, Ks, sh_degree, antialiased, radius_clip=0.0):
    proj = fully_fused_projection(means, quats, scales, viewmats, Ks, WIDTH, HEIGHT, opacities=opacities,
                                  radius_clip=radius_clip, calc_compensations=antialiased)
    opacities_c = opacities[None].expand(viewmats.shape[0], -1)
    if antialiased:
        opacities_c = opacities_c * proj.compensations
    visible = (proj.radii > 0).all(-1)
    campos = torch.linalg.inv(viewmats)[:, :3, 3]
    dirs = means[None] - campos[:, None]
    colors = sh_to_rgb(sh_degree, dirs, shs[None].expand(viewmats.shape[0], -1, -1, -1), masks=visible)
    return proj.radii, proj.means2d, proj.depths, proj.conics, opacities_c, colors


def fast(means, quats, scales, opacities, shs, viewmats, Ks, sh_degree, antialiased, radius_clip=0.0):
    return tuple(project_and_shade_cpu(means, quats, scales, opacities, shs, viewmats, Ks, WIDTH, HEIGHT,
                                       sh_degree=sh_degree, eps2d=0.3, near_plane=0.01, far_plane=1e10,
                                       radius_clip=radius_clip, antialiased=antialiased))


NAMES = ("radii", "means2d", "depths", "conics", "opacities", "colors")


@pytest.mark.parametrize("dtype, atol", [(torch.float64, 1e-9), (torch.float32, 1e-5)])
@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_forward_matches_reference(dtype, atol, antialiased, sh_degree):
    inputs = scene(dtype=dtype)
    ref = reference(*inputs, sh_degree, antialiased)
    out = fast(*inputs, sh_degree, antialiased)
    visible = (ref[0] > 0).all(-1)
    assert 0.3 < visible.float().mean() < 0.95  # both culled and kept pairs are exercised
    # the fast path computes in float64: in float32 a radius may differ by one pixel at a rounding tie of ceil()
    radius_diff = (out[0] - ref[0]).abs()
    assert radius_diff.max() <= (0 if dtype == torch.float64 else 1)
    assert torch.equal(out[0] > 0, ref[0] > 0)
    for name, a, e in zip(NAMES[1:], out[1:], ref[1:]):
        scale = max(1.0, float(e.abs().max())) if name in ("means2d", "conics") else 1.0
        torch.testing.assert_close(a, e, rtol=0, atol=atol * scale, msg=lambda m: f"{name}: {m}")  # noqa: B023 (called at once)


def _loss_weights(outputs, seed):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in outputs[1:]]


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("sh_degree", [1, 3])
def test_gradients_match_reference(antialiased, sh_degree):
    """Every input's gradient (viewmats included) for a random linear loss on every differentiable output."""
    results = []
    for fn in (fast, reference):
        leaves = [t.clone().requires_grad_(True) for t in scene(dtype=torch.float64)[:6]]
        Ks = scene(dtype=torch.float64)[6]
        outputs = fn(*leaves, Ks, sh_degree, antialiased)
        weights = _loss_weights(outputs, seed=7)
        sum((o * w).sum() for o, w in zip(outputs[1:], weights)).backward()
        results.append([t.grad for t in leaves])
    for name, a, e in zip(("means", "quats", "scales", "opacities", "shs", "viewmats"), *results):
        assert e.abs().max() > 0, f"{name}: reference gradient is zero (vacuous)"
        floor = 1e-9 * float(e.abs().max())
        torch.testing.assert_close(a, e, rtol=1e-4, atol=floor, msg=lambda m: f"{name}: {m}")  # noqa: B023 (called at once)
        # float64 on both sides: far tighter than the 1e-4 contract
        assert float((a - e).abs().max()) <= 1e-9 * max(1.0, float(e.abs().max())), name


@pytest.mark.parametrize("antialiased", [False, True])
def test_float64_gradcheck(antialiased):
    means, quats, scales, opacities, shs, viewmats, Ks = scene(n=12, n_cameras=2, seed=3)
    opacities = 0.2 + 0.7 * opacities  # away from the 1/255 cull, a discontinuity
    means[:, 2] = means[:, 2].abs() + 1.0  # in front of the cameras

    def f(means, quats, scales, opacities, shs, viewmats):
        return fast(means, quats, scales, opacities, shs, viewmats, Ks, 3, antialiased)[1:]

    inputs = [t.clone().requires_grad_(True) for t in (means, quats, scales, opacities, shs, viewmats)]
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-5)


def test_results_do_not_depend_on_the_thread_count():
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread only")
    before = numba.get_num_threads()
    runs = []
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            leaves = [t.clone().requires_grad_(True) for t in scene(n=2000, dtype=torch.float32)[:6]]
            Ks = scene(n=2000, dtype=torch.float32)[6]
            outputs = fast(*leaves, Ks, 3, True)
            weights = _loss_weights(outputs, seed=1)
            sum((o * w.float()).sum() for o, w in zip(outputs[1:], weights)).backward()
            runs.append([o.detach() for o in outputs] + [t.grad for t in leaves])
    finally:
        numba.set_num_threads(before)
    for a, b in zip(*runs):
        assert torch.equal(a, b)


def test_culled_pairs_have_zero_outputs_and_no_gradient():
    leaves = [t.clone().requires_grad_(True) for t in scene(dtype=torch.float64)[:6]]
    Ks = scene(dtype=torch.float64)[6]
    radii, means2d, depths, conics, opacities_c, colors = fast(*leaves, Ks, 3, True)
    culled = ~(radii > 0).all(-1)
    assert culled.any()
    for t in (means2d, conics):
        assert (t[culled] == 0).all()
    assert (depths[culled] == 0).all() and (opacities_c[culled] == 0).all()
    assert (colors[culled] == 0.5).all()
    # a loss on culled pairs only gives every Gaussian a zero gradient
    (means2d[culled].sum() + depths[culled].sum() + conics[culled].sum() + colors[culled].sum()).backward()
    for t in leaves:
        assert t.grad is None or (t.grad == 0).all()


@pytest.mark.parametrize("field, index", [("means", 0), ("quats", 1), ("scales", 2), ("opacities", 3), ("shs", 4)])
def test_non_finite_input_is_found_in_the_kernel(field, index):
    from kc_splatfacto.render import NonFiniteInputError

    inputs = scene(n=50, dtype=torch.float32)
    kept = int(torch.nonzero((fast(*inputs, 3, False)[0] > 0).all(-1).any(0))[-1])
    inputs[index] = inputs[index].clone()
    # SH coefficients are checked where they are read (active degrees of kept pairs): poison a kept Gaussian's
    # last degree-3 coefficient; the other inputs are checked for every Gaussian
    inputs[index][kept].view(-1)[-1] = math.inf
    name = "colors" if field == "shs" else field
    with pytest.raises(NonFiniteInputError, match=f"{name} holds 1 NaN/inf"):
        fast(*inputs, 3, False)


def test_non_finite_sh_coefficient_of_an_inactive_degree_is_not_read():
    inputs = scene(n=50, dtype=torch.float32)
    inputs[4] = inputs[4].clone()
    inputs[4][:, 4:] = math.nan  # degrees 2 and 3, unused at degree 1
    out = fast(*inputs, 1, False)
    assert all(torch.isfinite(t).all() for t in out)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sh_degree", [0, 1, 3])
def test_split_sh_coefficients_give_the_same_outputs_and_gradients(dtype, sh_degree):
    """``SplitSH(dc, rest)`` (Splatfacto's two parameters, read in place) against the same coefficients in one tensor:
    outputs and every gradient bit for bit (same kernel arithmetic), and the SH gradient against the torch reference."""
    from kc_splatfacto.render.sh import SplitSH

    results = []
    for split in (False, True):
        leaves = [t.clone().requires_grad_(True) for t in scene(dtype=dtype)[:4]]
        shs = scene(dtype=dtype)[4]
        dc = shs[:, :1].clone().requires_grad_(True)
        rest = shs[:, 1:].clone().requires_grad_(True)
        viewmats, Ks = scene(dtype=dtype)[5:]
        colors = SplitSH(dc, rest) if split else torch.cat([dc, rest], dim=1)
        outputs = fast(*leaves, colors, viewmats, Ks, sh_degree, False)
        weights = _loss_weights(outputs, seed=5)
        sum((o * w.to(dtype)).sum() for o, w in zip(outputs[1:], weights)).backward()
        results.append([o.detach() for o in outputs] + [t.grad for t in leaves] + [dc.grad, rest.grad])
    for a, b in zip(*results):
        assert torch.equal(a, b)
    # the reference's SH gradient for the same loss (float64 only: it is the tight oracle)
    if dtype == torch.float64:
        shs = scene(dtype=dtype)[4].clone().requires_grad_(True)
        outputs = reference(*scene(dtype=dtype)[:4], shs, *scene(dtype=dtype)[5:], sh_degree, False)
        weights = _loss_weights(outputs, seed=5)
        sum((o * w).sum() for o, w in zip(outputs[1:], weights)).backward()
        dc_grad, rest_grad = results[1][-2:]
        torch.testing.assert_close(torch.cat([dc_grad, rest_grad], dim=1), shs.grad, rtol=1e-9, atol=1e-12)
        assert shs.grad[:, : (sh_degree + 1) ** 2].abs().max() > 0


def test_split_sh_with_a_non_finite_coefficient_names_colors():
    from kc_splatfacto.render import NonFiniteInputError
    from kc_splatfacto.render.sh import SplitSH

    inputs = scene(n=50, dtype=torch.float32)
    kept = int(torch.nonzero((fast(*inputs, 3, False)[0] > 0).all(-1).any(0))[-1])
    dc, rest = inputs[4][:, :1].clone(), inputs[4][:, 1:].clone()
    dc[kept, 0, 1] = math.nan
    with pytest.raises(NonFiniteInputError, match="colors holds 1 NaN/inf"):
        fast(*inputs[:4], SplitSH(dc, rest), *inputs[5:], 3, False)


def test_split_sh_shapes_are_checked():
    from kc_splatfacto.render.sh import SplitSH

    inputs = scene(n=20, dtype=torch.float32)
    with pytest.raises(ValueError, match="SplitSH needs dc"):
        fast(*inputs[:4], SplitSH(inputs[4][:, :2], inputs[4][:, 2:]), *inputs[5:], 3, False)
