"""Density control: the tensor surgery keeps Adam state aligned, and the grow/prune/reset schedule of gsplat 1.5."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from kc_splatfacto.model import ops
from kc_splatfacto.model.gaussians import init_gaussian_params
from kc_splatfacto.model.mcmc import MCMCStrategy
from kc_splatfacto.model.strategy import PARAMETER_NAMES, DefaultStrategy, DensityStrategy, NoGaussiansLeftError


def make_params(n=6, seed=0):
    g = torch.Generator().manual_seed(seed)
    points = torch.rand(n, 3, generator=g)
    colors = (torch.rand(n, 3, generator=g) * 255).to(torch.uint8)
    return init_gaussian_params(points, colors, sh_degree=1, generator=g)


def adam_after_one_step(params):
    optimizers = {k: torch.optim.Adam([p], lr=1e-2) for k, p in params.items()}
    for p in params.values():
        p.grad = torch.randn_like(p)
    for opt in optimizers.values():
        opt.step()
        opt.zero_grad(set_to_none=True)
    return optimizers


def exp_avg(optimizers, params, name):
    return optimizers[name].state[params[name]]["exp_avg"]


def test_duplicate_appends_copies_with_zero_moments():
    params = make_params()
    optimizers = adam_after_one_step(params)
    before = {k: p.detach().clone() for k, p in params.items()}
    avg_before = exp_avg(optimizers, params, "means").clone()
    state = {"grad2d": torch.arange(6.0), "scene_scale": 1.0}
    mask = torch.tensor([False, True, False, True, False, False])
    ops.duplicate(params, optimizers, state, mask)
    assert len(params["means"]) == 8
    for k, p in params.items():
        assert torch.equal(p[:6], before[k])
        assert torch.equal(p[6:], before[k][[1, 3]])
        assert optimizers[k].param_groups[0]["params"][0] is p
    avg = exp_avg(optimizers, params, "means")
    assert torch.equal(avg[:6], avg_before) and torch.equal(avg[6:], torch.zeros(2, 3))
    assert torch.equal(state["grad2d"], torch.tensor([0, 1, 2, 3, 4, 5, 1, 3.0]))
    # the rewritten optimizer still steps
    for p in params.values():
        p.grad = torch.ones_like(p)
    for opt in optimizers.values():
        opt.step()


def test_split_samples_children_from_the_parent_gaussian():
    params = make_params(n=5)
    optimizers = adam_after_one_step(params)
    before = {k: p.detach().clone() for k, p in params.items()}
    mask = torch.tensor([True, False, False, True, False])
    torch.manual_seed(123)
    ops.split(params, optimizers, {"count": torch.ones(5)}, mask, n_samples=2)
    torch.manual_seed(123)
    noise = torch.randn(2, 2, 3).double().numpy()
    assert len(params["means"]) == 3 + 4
    assert torch.equal(params["means"][:3], before["means"][[1, 2, 4]])
    # oracle: scipy's rotation matrix (xyzw order) applied to scale * noise
    sel = [0, 3]
    quats = before["quats"][sel].double().numpy()
    rot = Rotation.from_quat(quats[:, [1, 2, 3, 0]]).as_matrix()
    scales = np.exp(before["scales"][sel].double().numpy())
    expected = before["means"][sel].double().numpy()[None] + np.einsum("nij,bnj->bni", rot, scales[None] * noise)
    np.testing.assert_allclose(params["means"][3:].detach().numpy(), expected.reshape(-1, 3), atol=1e-5)
    np.testing.assert_allclose(
        params["scales"][3:].detach().exp().numpy(), np.tile(scales / 1.6, (2, 1)), rtol=1e-5
    )
    assert torch.equal(params["features_dc"][3:], before["features_dc"][sel].repeat(2, 1))
    avg = exp_avg(optimizers, params, "scales")
    assert torch.equal(avg[3:], torch.zeros(4, 3))


def test_remove_keeps_rows_and_moments_aligned():
    params = make_params()
    optimizers = adam_after_one_step(params)
    avg_before = exp_avg(optimizers, params, "opacities").clone()
    before = params["opacities"].detach().clone()
    state = {"grad2d": torch.arange(6.0), "count": torch.ones(6), "scene_scale": 2.0}
    mask = torch.tensor([True, False, True, False, False, True])
    ops.remove(params, optimizers, state, mask)
    keep = [1, 3, 4]
    assert torch.equal(params["opacities"], before[keep])
    assert torch.equal(exp_avg(optimizers, params, "opacities"), avg_before[keep])
    assert torch.equal(state["grad2d"], torch.tensor([1.0, 3.0, 4.0])) and state["scene_scale"] == 2.0


def test_reset_opacity_clamps_and_zeroes_moments():
    params = make_params()
    with torch.no_grad():
        params["opacities"][:3] = 3.0  # sigmoid ~0.95
        params["opacities"][3:] = -4.0  # ~0.018
    optimizers = adam_after_one_step(params)
    low = params["opacities"][3:].detach().clone()
    ops.reset_opa(params, optimizers, {}, value=0.2)
    opa = torch.sigmoid(params["opacities"]).detach()
    assert torch.allclose(opa[:3], torch.full((3, 1), 0.2), atol=1e-6)
    assert torch.equal(params["opacities"][3:], low)
    state = optimizers["opacities"].state[params["opacities"]]
    assert torch.count_nonzero(state["exp_avg"]) == 0 and torch.count_nonzero(state["exp_avg_sq"]) == 0


def synthetic_info(grads, radii, width=100, height=50):
    means2d = torch.zeros(1, len(grads), 2, requires_grad=True)
    means2d.absgrad = torch.tensor(grads, dtype=torch.float32)[None]
    means2d.grad = torch.zeros_like(means2d)
    return {"means2d": means2d, "radii": torch.tensor(radii, dtype=torch.int32)[None], "width": width,
            "height": height, "n_cameras": 1}


def test_grow_and_prune_decisions_follow_the_thresholds():
    n = 4
    params = make_params(n)
    with torch.no_grad():
        params["scales"][:] = math.log(0.001)
        params["scales"][1] = math.log(0.5)  # large: split
        params["opacities"][:] = 2.0
        params["opacities"][3] = -5.0  # opacity 0.0067: pruned
    optimizers = adam_after_one_step(params)
    strategy = DefaultStrategy(prune_opa=0.1, grow_grad2d=0.0008, grow_scale3d=0.01, absgrad=True,
                               refine_start_iter=0, refine_every=1, reset_every=1000, refine_stop_iter=1000)
    state = strategy.initialize_state(scene_scale=1.0)
    # scaled gradient norm = |(gx * W/2, gy * H/2)|: 0 -> 0.001 (high), 1 -> high, 2 -> 0.0005 (low), 3 -> high
    grads = [[0.001 / 50, 0.0], [0.0, 0.002 / 25], [0.0005 / 50, 0.0], [0.001 / 50, 0.0]]
    radii = [[3, 3], [3, 3], [3, 3], [3, 3]]
    report = strategy.step_post_backward(params, optimizers, state, step=1, info=synthetic_info(grads, radii))
    assert report["duplicated"] == 2  # 0 and 3 are small with high gradient
    assert report["split"] == 1  # 1 is large
    assert report["pruned"] == 2  # 3 and its duplicate
    # survivors: 0, 2 (untouched), duplicate of 0, two children of 1
    assert len(params["means"]) == 5
    assert torch.count_nonzero(state["grad2d"]) == 0 and len(state["grad2d"]) == 5


def test_invisible_gaussians_accumulate_nothing():
    params = make_params(3)
    strategy = DefaultStrategy(absgrad=False, refine_start_iter=10)
    state = strategy.initialize_state()
    info = synthetic_info([[0.0, 0.0]] * 3, [[2, 2], [0, 0], [2, 0]])
    info["means2d"].grad = torch.tensor([[[0.3, 0.4], [1.0, 1.0], [1.0, 1.0]]])
    strategy.step_post_backward(params, {}, state, step=1, info=info)
    assert torch.allclose(state["grad2d"], torch.tensor([math.hypot(0.3 * 50, 0.4 * 25), 0, 0]))
    assert torch.equal(state["count"], torch.tensor([1.0, 0.0, 0.0]))


def test_opacity_reset_on_schedule():
    params = make_params(3)
    with torch.no_grad():
        params["opacities"][:] = 4.0
    strategy = DefaultStrategy(prune_opa=0.1, refine_start_iter=100, reset_every=20, refine_stop_iter=1000)
    state = strategy.initialize_state()
    info = synthetic_info([[0.0, 0.0]] * 3, [[1, 1]] * 3)
    for step in range(1, 20):
        strategy.step_post_backward(params, {}, state, step, info)
    assert torch.all(torch.sigmoid(params["opacities"]) > 0.9)
    report = strategy.step_post_backward(params, {}, state, 20, info)
    assert report["opacity_reset"] == 1
    assert torch.allclose(torch.sigmoid(params["opacities"]), torch.full((3, 1), 0.2), atol=1e-6)


def test_pruning_everything_is_a_clear_error():
    params = make_params(3)
    with torch.no_grad():
        params["opacities"][:] = -10.0
    strategy = DefaultStrategy(prune_opa=0.1, refine_start_iter=0, refine_every=1)
    state = strategy.initialize_state()
    with pytest.raises(NoGaussiansLeftError, match="removed every Gaussian"):
        strategy.step_post_backward(params, {}, state, 1, synthetic_info([[0.0, 0.0]] * 3, [[1, 1]] * 3))


def test_real_render_fills_absgrad_for_visible_gaussians():
    from kc_splatfacto.render import rasterization

    torch.manual_seed(0)
    n = 50
    params = init_gaussian_params(torch.rand(n, 3) - 0.5, None, sh_degree=0)
    viewmat = torch.eye(4)
    viewmat[2, 3] = 3.0
    K = torch.tensor([[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]])
    strategy = DefaultStrategy(absgrad=True, refine_start_iter=100)
    state = strategy.initialize_state()
    render, _, info = rasterization(params["means"], params["quats"], params["scales"].exp(),
                                    torch.sigmoid(params["opacities"]).squeeze(-1), torch.sigmoid(params["features_dc"]),
                                    viewmat[None], K[None], 32, 24, absgrad=True, rasterizer="cpu")
    strategy.step_pre_backward(params, {}, state, 0, info)
    render.square().sum().backward()
    strategy.step_post_backward(params, {}, state, 1, info)
    visible = (info["radii"][0] > 0).all(-1)
    assert visible.any()
    assert torch.equal(state["count"] > 0, visible)
    expected = (info["means2d"].absgrad[0] * torch.tensor([16.0, 12.0])).norm(dim=-1)
    assert torch.allclose(state["grad2d"], torch.where(visible, expected, torch.zeros_like(expected)))


def test_growth_cap_keeps_the_highest_gradient_candidates():
    n = 5
    params = make_params(n)
    with torch.no_grad():
        params["scales"][:] = math.log(0.001)  # all small: duplication, one new Gaussian each
        params["opacities"][:] = 2.0
    strategy = DefaultStrategy(prune_opa=0.1, grow_grad2d=0.0008, absgrad=True, refine_start_iter=0, refine_every=1,
                               reset_every=1000, max_gaussians=7)
    state = strategy.initialize_state()
    norms = [0.002, 0.005, 0.0001, 0.003, 0.004]  # four above the threshold, room for two
    grads = [[g / 50, 0.0] for g in norms]
    before = params["means"].detach().clone()
    report = strategy.step_post_backward(params, {}, state, 1, synthetic_info(grads, [[2, 2]] * n))
    assert report["duplicated"] == 2 and len(params["means"]) == 7
    assert torch.equal(params["means"][5:], before[[1, 4]])  # the two largest gradients


@pytest.mark.parametrize("track_radii", [False, True])
def test_compiled_statistics_pass_equals_the_torch_ops(monkeypatch, track_radii):
    """The numba pass (one CPU camera) against the torch ops it replaces and a float64 reference: counts and radii
    equal, the accumulated norms within one float32 ulp of float64 (and, on x86, bit-identical to torch's)."""
    rng = np.random.default_rng(3)
    n = 20_000
    scale = 10.0 ** rng.uniform(-9, -2, (n, 1))
    grads = (rng.standard_normal((n, 2)) * scale).astype(np.float32)
    radii = rng.integers(-1, 40, (n, 2)).astype(np.int32)
    start = rng.random(n).astype(np.float32) * 1e-3
    results = {}
    for path in ("kernel", "torch"):
        if path == "torch":
            monkeypatch.setenv("KC_SPLATFACTO_BACKEND", "torch")
        strategy = DefaultStrategy(absgrad=True, refine_start_iter=10, refine_scale2d_stop_iter=100 if track_radii else 0)
        state = strategy.initialize_state()
        state["grad2d"] = torch.from_numpy(start.copy())
        state["count"] = torch.full((n,), 2.0)
        if track_radii:
            state["radii"] = torch.from_numpy(start.copy() * 100)
        info = synthetic_info(grads.tolist(), radii.tolist(), width=97, height=61)
        for step in (1, 2):  # twice: the pass accumulates into its state
            strategy.step_post_backward(make_params(n), {}, state, step, info)
        results[path] = state
    kernel, ops_path = results["kernel"], results["torch"]
    assert torch.equal(kernel["count"], ops_path["count"])
    if track_radii:
        assert torch.equal(kernel["radii"], ops_path["radii"])
    visible = (radii > 0).all(-1)
    scaled = grads.astype(np.float64) * np.array([97 / 2.0, 61 / 2.0])
    once = np.float32(np.hypot(scaled[:, 0], scaled[:, 1]))
    expected = start.astype(np.float64) + 2 * np.where(visible, once.astype(np.float64), 0.0)
    np.testing.assert_allclose(kernel["grad2d"].numpy(), expected, rtol=3e-7, atol=0)
    torch.testing.assert_close(kernel["grad2d"], ops_path["grad2d"], rtol=2.4e-7, atol=0)
    assert int((kernel["count"] > 2).sum()) == int(visible.sum()) > 0


THRESHOLD = 2.0**-10  # a power of two: |(g, 0)| is exactly g in float32, so "exactly at the threshold" is exact
ABOVE = float(np.nextafter(np.float32(THRESHOLD), np.float32(1.0)))  # one float32 ulp above


@pytest.mark.parametrize("path", ["compiled", "torch"])
def test_short_run_pins_the_schedule_and_the_counts_at_its_boundary_steps(path):
    """Five Gaussians through 140 steps of gsplat's schedule (refine every 10 from step 0, opacity reset every 100,
    refinement paused for 30 steps after each reset), with gradients only at step 30. Hand-computed expectations:

    - refinements at 30..90 and 130, 140 (10, 20 and 100..120 fall in the pause: step % 100 < 30);
    - step 30: A (gradient exactly at the threshold) does not grow, B (one ulp above, small) is duplicated,
      C (above, large) is split in two, D (opacity 0.05 < 0.1) is pruned; C's children (scale 0.5 / 1.6 > 0.1 x scene
      scale) survive because size pruning starts only after the first reset;
    - step 100: the opacity reset (to 2 x 0.1); step 130, the first refinement after it, prunes C's two children.
    """
    from kc_splatfacto import backend

    n = 5
    params = make_params(n, seed=1)
    with torch.no_grad():
        params["means"][:, 0] = torch.arange(n, dtype=torch.float32)
        params["means"][4, 0] = 100.0  # E: visible at every step (its zero gradient only counts visits)
        params["scales"][:] = math.log(0.001)
        params["scales"][2] = math.log(0.5)  # C: large
        params["opacities"][:] = math.log(0.9 / 0.1)
        params["opacities"][3] = math.log(0.05 / 0.95)  # D: transparent
    strategy = DefaultStrategy(prune_opa=0.1, grow_grad2d=THRESHOLD, grow_scale3d=0.01, prune_scale3d=0.1,
                               refine_start_iter=0, refine_every=10, reset_every=100, pause_refine_after_reset=30,
                               refine_stop_iter=1000, absgrad=True)
    state = strategy.initialize_state(scene_scale=1.0)
    refined, resets, counts = [], [], {}
    torch.manual_seed(0)  # the split samples its children
    with backend.torch_reference(path == "torch"):
        for step in range(1, 141):
            count = len(params["means"])
            visible = params["means"][:, 0] > 50
            grads = [[0.0, 0.0] for _ in range(count)]
            if step == 30:
                visible[:3] = True
                grads[0], grads[1], grads[2] = [THRESHOLD, 0.0], [ABOVE, 0.0], [ABOVE, 0.0]
            radii = [[2, 2] if v else [0, 0] for v in visible.tolist()]
            # width 2, height 2, one camera: the NDC scaling of the gradient is 1
            report = strategy.step_post_backward(params, {}, state, step, synthetic_info(grads, radii, 2, 2))
            if float(state["count"].max()) == 0:  # E's visit count is zeroed only by a refinement
                refined.append(step)
            if report["opacity_reset"]:
                resets.append(step)
            if any(report[k] for k in ("duplicated", "split", "pruned")):
                counts[step] = (report["duplicated"], report["split"], report["pruned"], len(params["means"]))
    assert refined == [30, 40, 50, 60, 70, 80, 90, 130, 140]
    assert resets == [100]
    # (duplicated, split, pruned, Gaussians after): 5 + 1 (B's copy) + 1 (C -> 2 children) - 1 (D) = 6; then 6 - 2
    assert counts == {30: (1, 1, 1, 6), 130: (0, 0, 2, 4)}
    np.testing.assert_allclose(torch.sigmoid(params["opacities"]).detach().flatten().numpy(), 0.2, rtol=1e-6)


@pytest.mark.parametrize("revised", [False, True])
def test_split_children_opacity_with_and_without_the_revised_formula(revised):
    # Rota Bulo et al.'s revised opacity: each child gets 1 - sqrt(1 - o) (o = 0.64 -> 0.4); otherwise a copy of o
    params = make_params(1)
    with torch.no_grad():
        params["scales"][:] = math.log(0.5)
        params["opacities"][:] = math.log(0.64 / 0.36)
    strategy = DefaultStrategy(grow_grad2d=THRESHOLD, refine_start_iter=0, refine_every=1, revised_opacity=revised,
                               absgrad=True)
    state = strategy.initialize_state(scene_scale=1.0)
    report = strategy.step_post_backward(params, {}, state, 1, synthetic_info([[ABOVE, 0.0]], [[2, 2]], 2, 2))
    assert report["split"] == 1 and len(params["means"]) == 2
    expected = 1 - math.sqrt(1 - 0.64) if revised else 0.64
    np.testing.assert_allclose(torch.sigmoid(params["opacities"]).detach().flatten().numpy(), [expected] * 2, rtol=1e-5)


@pytest.mark.parametrize("make", [lambda: DefaultStrategy(max_gaussians=None), lambda: MCMCStrategy(cap_max=500)])
def test_both_strategies_have_the_interface_and_a_cap_only_lowers(make):
    """The training loop holds either through DensityStrategy alone: a cap lowers the growth limit, never raises it,
    and the sanity check names a missing parameter."""
    strategy = make()
    assert isinstance(strategy, DensityStrategy)
    limit = "max_gaussians" if isinstance(strategy, DefaultStrategy) else "cap_max"
    strategy.cap(300)
    strategy.cap(400)
    assert getattr(strategy, limit) == 300
    params = {name: torch.zeros(4, 3) for name in PARAMETER_NAMES}
    optimizers = {name: object() for name in PARAMETER_NAMES}
    strategy.check_sanity(params, optimizers)
    del optimizers["opacities"]
    with pytest.raises(KeyError, match="missing \\['opacities'\\]"):
        strategy.check_sanity(params, optimizers)
