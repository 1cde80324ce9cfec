"""The CPU path's pieces: viewmats as nerfstudio's own ``get_viewmat`` makes them; gsplat 1.4's ``info`` contract
(radii [C, N]); LPIPS with torchmetrics' call contract giving the official LPIPS values, and the one line a missing
weight file gives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from kc_splatfacto.nerfstudio_plugin.cpu import OfflineLPIPS, rasterization_gsplat_1_4, viewmats_from_camera_to_worlds
from tests.conftest import shared_scene


def _random_camera_to_worlds(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    w, x, y, z = q.unbind(-1)
    rotation = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1).reshape(n, 3, 3)
    return torch.cat([rotation, torch.randn(n, 3, 1, generator=g)], dim=-1)


def test_viewmats_are_the_inverse_camera_pose_in_opencv_axes():
    c2w = _random_camera_to_worlds(5).double()
    viewmats = viewmats_from_camera_to_worlds(c2w)
    opencv = torch.cat([c2w, torch.tensor([[[0, 0, 0, 1.0]]], dtype=c2w.dtype).expand(5, 1, 4)], dim=1)
    opencv[:, :3, 1:3] *= -1  # OpenGL (x right, y up, z back) -> OpenCV (x right, y down, z forward)
    assert torch.allclose(viewmats, torch.linalg.inv(opencv), atol=1e-12)


def test_viewmats_equal_nerfstudios_get_viewmat():
    splatfacto = pytest.importorskip("nerfstudio.models.splatfacto", reason="nerfstudio is not installed here")
    original = splatfacto.get_viewmat._torchdynamo_orig_callable  # the function torch.compile wraps
    c2w = _random_camera_to_worlds(4, seed=1)
    assert torch.equal(viewmats_from_camera_to_worlds(c2w), original(c2w))


def test_the_info_has_gsplat_1_4s_radii_and_packed_is_refused():
    g = torch.Generator().manual_seed(0)
    n = 50
    means = torch.randn(n, 3, generator=g) * 0.3
    args = dict(means=means, quats=torch.randn(n, 4, generator=g), scales=torch.full((n, 3), 0.05),
                opacities=torch.full((n,), 0.5), colors=torch.rand(n, 3, generator=g),
                viewmats=viewmats_from_camera_to_worlds(torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3]]])),
                Ks=torch.tensor([[[40.0, 0, 16], [0, 40.0, 12], [0, 0, 1]]]), width=32, height=24)
    render, alpha, info = rasterization_gsplat_1_4(**args, packed=False, sparse_grad=False)
    assert render.shape == (1, 24, 32, 3) and alpha.shape == (1, 24, 32, 1)
    assert info["radii"].shape == (1, n) and (info["radii"] > 0).any()
    with pytest.raises(ValueError, match="packed=True"):
        rasterization_gsplat_1_4(**args, packed=True)


def _png(path: Path) -> torch.Tensor:
    import cv2

    image = cv2.imread(str(path), cv2.IMREAD_COLOR)[..., ::-1]
    return torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float() / 255


def test_offline_lpips_gives_the_official_values_with_torchmetrics_call_contract():
    example = shared_scene("lpips-example")
    lpips = OfflineLPIPS(normalize=True)
    if not lpips.available:
        pytest.skip(lpips.missing_reason)
    ref, p0, p1 = (_png(example / f"ex_{name}.png") for name in ("ref", "p0", "p1"))
    assert float(lpips(ref, p0)) == pytest.approx(0.722, abs=1e-3)  # the LPIPS repository's test_network.py
    assert float(lpips(ref, p1)) == pytest.approx(0.138, abs=1e-3)
    both = lpips(torch.cat([ref, ref]), torch.cat([p0, p1]))
    assert both.dim() == 0 and float(both) == pytest.approx((0.722 + 0.138) / 2, abs=1e-3)  # the batch's mean
    assert not dict(lpips.state_dict())  # its network is not part of a model's state dict


def test_offline_lpips_without_weights_says_how_to_install_them(monkeypatch):
    from kc_splatfacto.nerfstudio_plugin import cpu

    monkeypatch.setattr(cpu, "lpips_available", lambda net: "LPIPS (alex) needs the weight file ... pip install ...")
    lpips = cpu.OfflineLPIPS()
    assert not lpips.available and "pip install" in lpips.missing_reason
    assert torch.isnan(lpips(torch.rand(1, 3, 64, 64), torch.rand(1, 3, 64, 64)))
