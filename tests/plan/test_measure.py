"""The scene plan's measurements on scenes whose answer is known, against independent oracles (numpy, PyWavelets)."""

from __future__ import annotations

import numpy as np
import pytest
import pywt
import torch

from kc_splatfacto.losses.frequency import FrequencyLossConfig
from kc_splatfacto.plan import measure
from tests.plan import synthetic


def test_projection_matches_a_pinhole_written_out_point_by_point():
    cams, points = synthetic.ring(5)
    u, v, seen = measure.project(points, cams)
    for i in range(len(cams)):
        R, t = cams.viewmats[i, :3, :3].double().numpy(), cams.viewmats[i, :3, 3].double().numpy()
        K = cams.Ks[i].double().numpy()
        for m in range(0, len(points), 97):
            x = R @ points[m].double().numpy() + t
            pixel = K @ (x / x[2])
            assert u[i, m].item() == pytest.approx(pixel[0], abs=1e-6)
            assert v[i, m].item() == pytest.approx(pixel[1], abs=1e-6)
            inside = x[2] > 0 and 0 <= pixel[0] < synthetic.WIDTH and 0 <= pixel[1] < synthetic.HEIGHT
            assert bool(seen[i, m]) == inside


def test_a_forward_facing_capture_faces_every_point_from_every_view():
    coverage = measure.view_coverage(*reversed(synthetic.forward_facing(9)))
    assert coverage.views == 9 and coverage.points == 70
    assert coverage.in_frame == 1.0 and coverage.coverage == 1.0


def test_a_ring_round_an_object_faces_each_point_from_about_a_third_of_its_views():
    """Every point of the ball is in every frame, but the views facing its side (within 60 degrees of their mean
    direction) are about a third of a full ring (120 of 360 degrees seen from the centre; 0.30 measured here, as the
    points off the centre see the nearer cameras spread wider)."""
    coverage = measure.view_coverage(*reversed(synthetic.ring(24)))
    assert coverage.in_frame == pytest.approx(1.0, abs=0.02)
    assert 0.25 < coverage.coverage < 0.4


def test_no_seed_points_count_as_seen_by_every_view():
    cams, _ = synthetic.ring(4)
    assert measure.view_coverage(None, cams) == measure.Coverage(4, 0, 1.0, 1.0)


def test_a_lambertian_scene_has_no_colour_spread_and_a_view_dependent_one_has():
    cams, points = synthetic.forward_facing(9)
    rng = np.random.default_rng(1)
    base = rng.uniform(0.2, 0.8, size=(len(points), 3))
    background = synthetic.texture()
    lambertian = synthetic.draw(cams, points, np.broadcast_to(base, (9, *base.shape)), background)
    shift = np.linspace(-0.15, 0.15, 9)[:, None, None]  # each view sees every point 0.3 brighter or darker
    view_dependent = synthetic.draw(cams, points, np.clip(base + shift, 0, 1), background)
    flat = measure.colour_spread(lambertian, cams, points)
    shiny = measure.colour_spread(view_dependent, cams, points)
    assert flat.points == 70 and flat.spread < 1.0
    # MAD of 9 views evenly spread over 0.3 (in 8-bit levels): the median |shift - median| of 9 evenly spaced values
    expected = np.median(np.abs(shift.ravel() - np.median(shift))) * 255
    assert shiny.spread == pytest.approx(expected, abs=1.5)


def test_a_white_backdrop_is_white_at_the_border():
    white = torch.full((40, 60, 3), 255, dtype=torch.uint8)
    white[10:30, 20:40] = 90  # the object
    border = measure.border_colour([white, white])
    assert border.white == 1.0 and border.black == 0.0
    textured = torch.tensor(np.round(synthetic.texture() * 255), dtype=torch.uint8)
    assert measure.border_colour([textured]).white == 0.0


def _pywt_details(gray: np.ndarray, wave: str, levels: int):
    return pywt.wavedec2(gray, wave, mode="symmetric", level=levels)[1:][::-1]  # finest first


def test_white_noise_is_at_its_own_floor_at_every_level_and_a_texture_is_above_it():
    rng = np.random.default_rng(2)
    sigma = 8.0
    noise = torch.tensor(np.clip(np.round(128 + rng.normal(0, sigma, (256, 256, 3))), 0, 255), dtype=torch.uint8)
    levels = measure.detail_levels([noise], "db3", 3)
    gray = noise.double().mean(-1).numpy() / 255  # the channel mean: noise of sigma / sqrt(3)
    assert levels.noise == pytest.approx(sigma / np.sqrt(3), rel=0.08)
    assert all(0.85 < snr < 1.2 for snr in levels.snr)
    details = _pywt_details(gray, "db3", 3)
    oracle_noise = np.median(np.abs(details[0][2])) / 0.6745
    rms = [np.sqrt(np.mean(np.square(np.stack(d)))) for d in details]
    assert levels.snr == pytest.approx([r / oracle_noise for r in rms], rel=1e-4)
    ramp = np.linspace(0, 1, 256)
    smooth_texture = 0.5 + 0.4 * np.sin(40 * ramp)[:, None] * np.cos(30 * ramp)[None, :]
    image = np.clip(smooth_texture[..., None] * 255 + rng.normal(0, 1.0, (256, 256, 1)), 0, 255)
    textured = measure.detail_levels([torch.tensor(np.round(np.repeat(image, 3, -1)), dtype=torch.uint8)], "db3", 3)
    assert textured.snr[2] > 10 * textured.snr[0]  # the texture's energy sits in the coarse levels


def test_the_coefficient_counts_are_pywavelets_band_sizes_at_the_first_stage():
    image = torch.zeros(128, 192, 3, dtype=torch.uint8)
    levels = measure.detail_levels([image], "db3", 3, downscale=1)
    shapes = [d[0].shape for d in _pywt_details(np.zeros((64, 96)), "db3", 3)]
    assert levels.coefficients == tuple(h * w for h, w in shapes)
    assert measure.detail_levels([image], "db3", 3, downscale=2).coefficients == tuple(
        h * w for h, w in [d[0].shape for d in _pywt_details(np.zeros((32, 48)), "db3", 2)])


def test_the_cbc_share_is_the_two_terms_on_the_ground_truth_as_numpy_and_pywavelets_compute_them():
    rng = np.random.default_rng(3)
    image = torch.tensor(rng.integers(0, 256, (64, 96, 3)), dtype=torch.uint8)
    config = FrequencyLossConfig()
    rgb = image.double().numpy() / 255
    wavelet = cov = 0.0
    for c in range(3):
        details = _pywt_details(rgb[..., c], config.wave, config.wavelet_levels)
        for j, bands in enumerate(details, start=1):
            wavelet += 2.0**j * sum(np.abs(b).mean() for b in bands) / 3  # mean over channels
            sigma = np.cov(np.stack([b.ravel() for b in bands]))
            cov += np.square(sigma - np.diag(np.diag(sigma))).sum() / 3
    expected = config.cbc_weight * cov / (config.wavelet_weight * wavelet)
    assert measure.cross_band_share([image], config) == pytest.approx(expected, rel=1e-3)
    assert measure.cross_band_share([image], FrequencyLossConfig(cbc_weight=0.0)) == 0.0


def test_the_noise_floor_of_the_colour_spread_is_the_mad_of_the_images_noise():
    """White noise of deviation 4 (8-bit levels) on mid-grey: the one-level Haar HH band's median |x| is 0.6745 x 4
    (the median absolute deviation of that noise), less a little for the rounding to 8 bits; a noise-free image
    has none."""
    cams, points = synthetic.forward_facing(4)
    rng = np.random.default_rng(0)
    noisy = [torch.tensor(np.clip(np.round(128 + rng.normal(0, 4, (synthetic.HEIGHT, synthetic.WIDTH, 3))), 0, 255),
                          dtype=torch.uint8) for _ in range(4)]
    assert measure.colour_spread(noisy, cams, points).noise == pytest.approx(0.6745 * 4, rel=0.1)
    flat = [torch.full((synthetic.HEIGHT, synthetic.WIDTH, 3), 90, dtype=torch.uint8)] * 4
    assert measure.colour_spread(flat, cams, points).noise == 0.0
