"""Spherical harmonics against the explicit real-SH polynomials (Condon-Shortley phase, as gsplat/Inria use them)
and against orthonormality on the sphere computed by exact quadrature."""

import math

import numpy as np
import pytest
import torch

from kc_splatfacto.render import sh_bases, sh_to_rgb, spherical_harmonics


def explicit_real_sh(x, y, z):
    """Real SH up to l=3 written out from their textbook normalizations, in gsplat's order (m = -l..l) and sign
    convention (odd m carry the Condon-Shortley factor -1)."""
    pi = math.pi
    return np.stack(
        [
            np.full_like(x, 0.5 * math.sqrt(1 / pi)),
            -math.sqrt(3 / (4 * pi)) * y,
            math.sqrt(3 / (4 * pi)) * z,
            -math.sqrt(3 / (4 * pi)) * x,
            0.5 * math.sqrt(15 / pi) * x * y,
            -0.5 * math.sqrt(15 / pi) * y * z,
            0.25 * math.sqrt(5 / pi) * (3 * z**2 - 1),
            -0.5 * math.sqrt(15 / pi) * x * z,
            0.25 * math.sqrt(15 / pi) * (x**2 - y**2),
            -0.25 * math.sqrt(35 / (2 * pi)) * y * (3 * x**2 - y**2),
            0.5 * math.sqrt(105 / pi) * x * y * z,
            -0.25 * math.sqrt(21 / (2 * pi)) * y * (5 * z**2 - 1),
            0.25 * math.sqrt(7 / pi) * z * (5 * z**2 - 3),
            -0.25 * math.sqrt(21 / (2 * pi)) * x * (5 * z**2 - 1),
            0.25 * math.sqrt(105 / pi) * z * (x**2 - y**2),
            -0.25 * math.sqrt(35 / (2 * pi)) * x * (x**2 - 3 * y**2),
        ],
        axis=-1,
    )


def unit_dirs(n, seed=0):
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return d / d.norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_bases_equal_explicit_polynomials(degree):
    d = unit_dirs(500)
    expected = explicit_real_sh(*d.numpy().T)[:, : (degree + 1) ** 2]
    np.testing.assert_allclose(sh_bases(degree, d).numpy(), expected, rtol=1e-12, atol=1e-13)


def test_bases_are_orthonormal_on_the_sphere():
    """Gauss-Legendre in cos(theta) x uniform phi is exact for these degree <= 6 products."""
    nodes, weights = np.polynomial.legendre.leggauss(8)
    phis = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ct, ph = np.meshgrid(nodes, phis, indexing="ij")
    st = np.sqrt(1 - ct**2)
    d = torch.from_numpy(np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3))
    w = torch.from_numpy((weights[:, None] * np.full_like(ph, 2 * np.pi / len(phis))).reshape(-1))
    Y = sh_bases(3, d)  # [P, 16]
    gram = (Y * w[:, None]).T @ Y
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-12, rtol=0)


def test_colors_use_normalized_directions_masks_and_offset_clamp():
    n = 64
    d = unit_dirs(n, seed=1)
    coeffs = torch.randn(n, 16, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    lengths = torch.rand(n, 1, dtype=torch.float64) * 10 + 0.1
    expected = np.einsum("nk,nkc->nc", explicit_real_sh(*d.numpy().T), coeffs.numpy())
    got = spherical_harmonics(3, d * lengths, coeffs)  # any direction length
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-11, atol=1e-12)
    # lower degree uses only the leading coefficients even when more are stored (partial SH bands)
    expected1 = np.einsum("nk,nkc->nc", explicit_real_sh(*d.numpy().T)[:, :4], coeffs[:, :4].numpy())
    np.testing.assert_allclose(spherical_harmonics(1, d, coeffs).numpy(), expected1, rtol=1e-11, atol=1e-12)
    masks = torch.arange(n) % 3 == 0
    masked = spherical_harmonics(3, d, coeffs, masks=masks)
    assert (masked[~masks] == 0).all()
    rgb = sh_to_rgb(3, d, coeffs)
    np.testing.assert_allclose(rgb.numpy(), np.maximum(expected + 0.5, 0.0), rtol=1e-11, atol=1e-12)
    assert (rgb == 0).any()  # the clamp really acted


def test_sh_gradients_finite_differences_and_zero_direction():
    d = unit_dirs(5, seed=4).requires_grad_(True)
    coeffs = torch.randn(5, 16, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda d, c: spherical_harmonics(3, d * 2.0, c), (d, coeffs))
    zero = torch.zeros(1, 3, dtype=torch.float64, requires_grad=True)
    out = spherical_harmonics(3, zero, coeffs[:1].detach())
    out.sum().backward()
    assert torch.isfinite(out).all() and torch.isfinite(zero.grad).all()


def test_bad_degree_or_too_few_coefficients_raise():
    with pytest.raises(ValueError, match="sh_degree"):
        sh_bases(4, unit_dirs(2))
    with pytest.raises(ValueError, match="needs 9 SH coefficients"):
        spherical_harmonics(2, unit_dirs(2), torch.zeros(2, 4, 3, dtype=torch.float64))
