"""Gaussian initialization (scales from 3 nearest neighbours, colours as SH) and the optimizer schedules."""

import math

import numpy as np
import torch

from kc_splatfacto.engine.optimizers import ExponentialDecay, OptimizersConfig
from kc_splatfacto.model.gaussians import (
    INITIAL_OPACITY,
    SH_C0,
    init_gaussian_params,
    knn_mean_distance,
    num_sh_bases,
)


def brute_force_knn_mean(points: np.ndarray, k: int) -> np.ndarray:
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    np.fill_diagonal(d, np.inf)
    return np.sort(d, axis=1)[:, :k].mean(axis=1)


def test_knn_mean_distance_matches_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(300, 3)).astype(np.float32)
    got = knn_mean_distance(torch.from_numpy(pts)).numpy()
    np.testing.assert_allclose(got, brute_force_knn_mean(pts.astype(np.float64), 3), rtol=1e-5)


def test_init_from_seed_points():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-1, 1, size=(100, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, size=(100, 3)).astype(np.uint8)
    params = init_gaussian_params(torch.from_numpy(pts), torch.from_numpy(rgb), sh_degree=3)
    assert set(params.keys()) == {"means", "scales", "quats", "features_dc", "features_rest", "opacities"}
    assert params["features_rest"].shape == (100, num_sh_bases(3) - 1, 3)
    assert torch.count_nonzero(params["features_rest"]) == 0
    expected_scale = np.log(brute_force_knn_mean(pts.astype(np.float64), 3))
    np.testing.assert_allclose(params["scales"].detach().numpy(), np.repeat(expected_scale[:, None], 3, 1), rtol=1e-5)
    # the degree-0 SH colour reproduces the seed colour
    np.testing.assert_allclose(params["features_dc"].detach().numpy() * SH_C0 + 0.5, rgb / 255.0, atol=1e-6)
    np.testing.assert_allclose(torch.sigmoid(params["opacities"]).detach().numpy(), INITIAL_OPACITY, rtol=1e-6)
    np.testing.assert_allclose(params["quats"].detach().norm(dim=-1).numpy(), 1.0, rtol=1e-5)


def test_duplicated_and_lonely_seed_points_get_finite_scales():
    pts = torch.tensor([[0.0, 0, 0], [0, 0, 0], [0, 0, 0], [0, 0, 0], [1, 1, 1]])
    params = init_gaussian_params(pts, None, sh_degree=0)
    assert torch.isfinite(params["scales"]).all()
    single = init_gaussian_params(torch.zeros(1, 3), None, sh_degree=0, scene_scale=2.0)
    assert torch.allclose(single["scales"].exp(), torch.full((1, 3), 0.02))


def test_random_init_fills_the_cube():
    params = init_gaussian_params(None, None, num_random=2000, random_scale=4.0, scene_scale=0.5,
                                  generator=torch.Generator().manual_seed(0))
    means = params["means"].detach()
    assert means.shape == (2000, 3)
    assert means.abs().max() <= 1.0 and means.abs().max() > 0.95  # side 4 * 0.5 = 2
    assert torch.isfinite(params["scales"]).all()


def test_sh_degree_zero_stores_colour_logits():
    rgb = torch.tensor([[255, 0, 128]], dtype=torch.uint8).repeat(4, 1)
    params = init_gaussian_params(torch.rand(4, 3), rgb, sh_degree=0)
    assert params["features_rest"].shape == (4, 0, 3)
    assert torch.allclose(torch.sigmoid(params["features_dc"][0]), rgb[0].float() / 255, atol=1e-6)


def test_exponential_decay_schedule():
    f = ExponentialDecay(1.6e-4, 1.6e-6, max_steps=1000)
    assert f(0) == 1.0
    assert math.isclose(f(1000) * 1.6e-4, 1.6e-6, rel_tol=1e-9)
    assert math.isclose(f(500) * 1.6e-4, math.sqrt(1.6e-4 * 1.6e-6), rel_tol=1e-9)
    assert f(5000) == f(1000)  # held at lr_final after max_steps
    warm = ExponentialDecay(1e-2, 1e-4, max_steps=100, warmup_steps=10, lr_pre_warmup=0.0)
    assert math.isclose(warm(5) * 1e-2, 5e-3)


def test_optimizer_groups_have_splatfacto_rates():
    params = init_gaussian_params(torch.rand(10, 3), None)
    optimizers, schedulers = OptimizersConfig().setup(params, steps_scale=100 / 30000)
    rates = {k: opt.param_groups[0]["lr"] for k, opt in optimizers.items()}
    assert rates == {"means": 1.6e-4, "features_dc": 0.0025, "features_rest": 0.0025 / 20, "opacities": 0.05,
                     "scales": 0.005, "quats": 0.001}
    assert all(opt.param_groups[0]["eps"] == 1e-15 for opt in optimizers.values())
    assert list(schedulers) == ["means"]
    for _ in range(100):
        optimizers["means"].step()
        schedulers["means"].step()
    assert math.isclose(optimizers["means"].param_groups[0]["lr"], 1.6e-6, rel_tol=1e-6)
