"""EWA projection against a float64 numpy re-derivation (scipy rotations, numpy inverses) and finite differences."""

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from kc_splatfacto.render import fully_fused_projection, quat_to_rotmat


def numpy_projection(means, quats, scales, opacities, viewmat, K, width, height, eps2d=0.3, near=0.01, far=1e10,
                     radius_clip=0.0, antialiased=False):
    """One camera, one Gaussian at a time, from the formulas of gsplat 1.5.3 (ProjectionEWA3DGSFused.cu)."""
    out = []
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    R_cam, t_cam = viewmat[:3, :3], viewmat[:3, 3]
    for mean, quat, scale, opacity in zip(means, quats, scales, opacities):
        w, x, y, z = quat
        rot = Rotation.from_quat([x, y, z, w]).as_matrix()  # scipy: scalar-last, normalizes
        cov = rot @ np.diag(scale**2) @ rot.T
        p = R_cam @ mean + t_cam
        cov_c = R_cam @ cov @ R_cam.T
        culled = dict(radii=(0, 0), mean2d=(0.0, 0.0), depth=0.0, conic=(0.0, 0.0, 0.0), comp=0.0)
        if not (near <= p[2] <= far):
            out.append(culled)
            continue
        u = np.clip(p[0] / p[2], -(cx / fx + 0.3 * 0.5 * width / fx), (width - cx) / fx + 0.3 * 0.5 * width / fx)
        v = np.clip(p[1] / p[2], -(cy / fy + 0.3 * 0.5 * height / fy), (height - cy) / fy + 0.3 * 0.5 * height / fy)
        J = np.array([[fx / p[2], 0, -fx * u / p[2]], [0, fy / p[2], -fy * v / p[2]]])
        cov2d = J @ cov_c @ J.T
        blurred = cov2d + eps2d * np.eye(2)
        comp = math.sqrt(max(0.0, np.linalg.det(cov2d) / np.linalg.det(blurred)))
        if np.linalg.det(blurred) <= 0:
            out.append(culled)
            continue
        conic = np.linalg.inv(blurred)
        eff = opacity * comp if antialiased else opacity
        if eff < 1 / 255:
            out.append(culled)
            continue
        extent = min(3.33, math.sqrt(2 * math.log(eff * 255)))
        rx, ry = math.ceil(extent * math.sqrt(blurred[0, 0])), math.ceil(extent * math.sqrt(blurred[1, 1]))
        m2 = (fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy)
        if rx <= radius_clip and ry <= radius_clip:
            out.append(culled)
            continue
        if m2[0] + rx <= 0 or m2[0] - rx >= width or m2[1] + ry <= 0 or m2[1] - ry >= height:
            out.append(culled)
            continue
        out.append(dict(radii=(rx, ry), mean2d=m2, depth=p[2], conic=(conic[0, 0], conic[0, 1], conic[1, 1]), comp=comp))
    return out


def scene(n=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * torch.tensor([1.5, 1.0, 1.0], dtype=torch.float64)
    means[:, 2] += 2.5  # some behind the camera / near plane, some far off-screen
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(-5, -1, generator=g))
    opacities = torch.rand(n, generator=g, dtype=torch.float64)
    angle = 0.3
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = torch.tensor(
        [[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1]], dtype=torch.float64
    ) @ torch.tensor([[1, 0, 0], [0, math.cos(0.2), -math.sin(0.2)], [0, math.sin(0.2), math.cos(0.2)]], dtype=torch.float64)
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=torch.float64)
    K = torch.tensor([[60.0, 0, 37.0], [0, 55.0, 22.0], [0, 0, 1]], dtype=torch.float64)
    return means, quats, scales, opacities, viewmat, K


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("radius_clip", [0.0, 2.0])
def test_projection_matches_numpy_rederivation(antialiased, radius_clip):
    width, height = 70, 50
    means, quats, scales, opacities, viewmat, K = scene()
    proj = fully_fused_projection(
        means, quats, scales, viewmat[None], K[None], width, height, opacities=opacities, radius_clip=radius_clip,
        calc_compensations=antialiased, near_plane=0.5, far_plane=4.5,
    )
    expected = numpy_projection(
        means.numpy(), quats.numpy(), scales.numpy(), opacities.numpy(), viewmat.numpy(), K.numpy(), width, height,
        near=0.5, far=4.5, radius_clip=radius_clip, antialiased=antialiased,
    )
    radii = np.array([e["radii"] for e in expected])
    np.testing.assert_array_equal(proj.radii[0].numpy(), radii)
    visible = (radii > 0).all(-1)
    # the scene exercises every branch: visible, near/far culled, off-screen, low opacity
    assert 30 < visible.sum() < 190
    np.testing.assert_allclose(proj.means2d[0].numpy(), np.array([e["mean2d"] for e in expected]), rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(proj.depths[0].numpy(), np.array([e["depth"] for e in expected]), rtol=1e-12)
    np.testing.assert_allclose(proj.conics[0].numpy(), np.array([e["conic"] for e in expected]), rtol=1e-8, atol=1e-12)
    if antialiased:
        np.testing.assert_allclose(
            proj.compensations[0].numpy(), np.array([e["comp"] for e in expected]), rtol=1e-8, atol=1e-12
        )
    else:
        assert proj.compensations is None


def test_projection_gradients_match_finite_differences():
    width, height = 70, 50
    means, quats, scales, opacities, viewmat, K = scene(n=12, seed=3)
    means = means * 0.3 + torch.tensor([0, 0, 1.8], dtype=torch.float64)  # all visible, some past the FOV clamp
    means[0, 0] = 4.0  # x/z beyond the clamp: the Jacobian uses the clamped value

    def project(means, quats, scales):
        proj = fully_fused_projection(means, quats, scales, viewmat[None], K[None], width, height, calc_compensations=True)
        return proj.means2d, proj.conics, proj.depths, proj.compensations

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales))
    assert (fully_fused_projection(*inputs, viewmat[None], K[None], width, height).radii > 0).all(-1).sum() >= 8
    assert torch.autograd.gradcheck(project, inputs, eps=1e-7, atol=1e-5, rtol=1e-5)


def test_quaternion_is_normalized_and_zero_quaternion_is_identity_without_nan():
    q = torch.tensor([[2.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [1.0, 2.0, -3.0, 0.5]], dtype=torch.float64,
                     requires_grad=True)
    rot = quat_to_rotmat(q)
    torch.testing.assert_close(rot[0], torch.eye(3, dtype=torch.float64))
    torch.testing.assert_close(rot[1], torch.eye(3, dtype=torch.float64))
    expected = Rotation.from_quat([2.0, -3.0, 0.5, 1.0]).as_matrix()
    np.testing.assert_allclose(rot[2].detach().numpy(), expected, atol=1e-12)
    rot.sum().backward()
    assert torch.isfinite(q.grad).all()


def test_near_far_and_low_opacity_culling_and_opacity_aware_radius():
    width, height = 64, 64
    K = torch.tensor([[[50.0, 0, 32], [0, 50.0, 32], [0, 0, 1]]])
    viewmat = torch.eye(4)[None]
    means = torch.tensor([[0, 0, 0.005], [0, 0, -1.0], [0, 0, 2.0], [0, 0, 2.0], [0, 0, 2.0], [0, 0, 200.0]])
    quats = torch.tensor([[1.0, 0, 0, 0]]).repeat(6, 1)
    scales = torch.full((6, 3), 0.1)
    opacities = torch.tensor([0.9, 0.9, 0.9, 0.02, 1.0 / 255 * 0.99, 0.9])
    proj = fully_fused_projection(means, quats, scales, viewmat, K, width, height, opacities=opacities, far_plane=100.0)
    radii = proj.radii[0]
    assert radii[0].tolist() == [0, 0]  # in front of the camera but before the near plane
    assert radii[1].tolist() == [0, 0]  # behind the camera
    assert radii[5].tolist() == [0, 0]  # beyond the far plane
    assert radii[4].tolist() == [0, 0]  # opacity below 1/255
    sigma = math.sqrt((50 * 0.1 / 2.0) ** 2 + 0.3)
    assert radii[2].tolist() == [math.ceil(3.33 * sigma)] * 2
    assert radii[3].tolist() == [math.ceil(math.sqrt(2 * math.log(0.02 * 255)) * sigma)] * 2
    assert (proj.depths[0, [0, 1, 4, 5]] == 0).all() and (proj.conics[0, [0, 1, 4, 5]] == 0).all()
