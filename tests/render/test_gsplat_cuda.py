"""gsplat's CUDA rasterizer (``rasterizer="gsplat"``) against the project's compiled CPU path on the same scenes.

Runs only where CUDA and gsplat 1.5.3 are both there (skipped otherwise, as on CI). Colours, alphas and every
gradient (means, quats, scales, opacities, colours or SH coefficients, viewmats, means2d and its absgrad) are compared
at the tolerances of the CPU-vs-reference tests (forward 1e-5 absolute; gradients 1e-4 relative with an absolute
floor of 1e-5 of the largest gradient), classic and antialiased. Set ``KC_PARITY_REPORT=path.json`` to also write the
largest differences (docs/results/gpu/ records a run).
"""

from __future__ import annotations

import json
import os

import pytest
import torch
import torch.nn.functional as F

from kc_splatfacto.render import rasterization


def _gsplat_cuda() -> bool:
    if not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401
    except Exception:
        return False
    return True


pytestmark = pytest.mark.skipif(not _gsplat_cuda(), reason="needs a CUDA GPU and gsplat (pip install gsplat==1.5.3)")

REPORT: dict[str, dict[str, float]] = {}


def random_scene(n: int = 3000, n_cameras: int = 2, width: int = 96, height: int = 64, sh_degree: int = 3, seed: int = 0):
    """N Gaussians in front of C cameras looking down +z, with SH coefficients [N, (d+1)^2, 3]."""
    g = torch.Generator().manual_seed(seed)
    means = torch.cat([(torch.rand(n, 2, generator=g) - 0.5) * 4.0, 2.0 + 4.0 * torch.rand(n, 1, generator=g)], dim=-1)
    quats = F.normalize(torch.randn(n, 4, generator=g), dim=-1)
    scales = torch.exp(torch.empty(n, 3).uniform_(-4.5, -2.0, generator=g))
    opacities = 0.05 + 0.9 * torch.rand(n, generator=g)
    colors = 0.3 * torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g)
    viewmats = torch.eye(4).repeat(n_cameras, 1, 1)
    for c in range(n_cameras):  # small sideways shifts and a slight yaw per camera
        angle = 0.05 * c
        viewmats[c, 0, 0], viewmats[c, 0, 2] = torch.cos(torch.tensor(angle)), torch.sin(torch.tensor(angle))
        viewmats[c, 2, 0], viewmats[c, 2, 2] = -torch.sin(torch.tensor(angle)), torch.cos(torch.tensor(angle))
        viewmats[c, 0, 3] = 0.1 * c
    f = 0.9 * width
    Ks = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]]).repeat(n_cameras, 1, 1)
    return dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmats=viewmats,
                Ks=Ks, width=width, height=height, sh_degree=sh_degree)


def garden_scene(garden_npz, downscale: int = 4):
    """gsplat's test_garden.npz as in its ``load_test_data`` (tests/render/test_garden.py), RGB colours, 1/4 size."""
    from tests.render.test_garden import load_garden

    garden = load_garden(str(garden_npz))
    Ks = garden["Ks"].clone()
    Ks[:, :2] /= downscale
    return dict(means=garden["means"], quats=garden["quats"], scales=garden["scales"],
                opacities=garden["opacities"], colors=garden["colors"], viewmats=garden["viewmats"], Ks=Ks,
                width=garden["width"] // downscale, height=garden["height"] // downscale, sh_degree=None)


LEAVES = ("means", "quats", "scales", "opacities", "colors", "viewmats")


def render_and_grads(scene: dict, device: str, backend: str, rasterize_mode: str, weights=None):
    """Forward + backward of a fixed random linear function of colours and alphas -> outputs, grads, weights."""
    leaves = {k: scene[k].detach().clone().to(device).requires_grad_(True) for k in LEAVES}
    colors, alphas, meta = rasterization(
        leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
        leaves["viewmats"], scene["Ks"].to(device), scene["width"], scene["height"], sh_degree=scene["sh_degree"],
        rasterize_mode=rasterize_mode, absgrad=True, rasterizer=backend,
        backgrounds=torch.full((scene["viewmats"].shape[0], 3), 0.25, device=device),
    )
    if weights is None:
        g = torch.Generator().manual_seed(1)
        weights = (torch.randn(colors.shape, generator=g), torch.randn(alphas.shape, generator=g))
    ((colors * weights[0].to(device)).sum() + (alphas * weights[1].to(device)).sum()).backward()
    grads = {k: v.grad.detach().cpu() for k, v in leaves.items()}
    grads["means2d"] = meta["means2d"].grad.detach().cpu()
    grads["absgrad"] = meta["means2d"].absgrad.detach().cpu()
    outputs = {"colors": colors.detach().cpu(), "alphas": alphas.detach().cpu(),
               "radii": meta["radii"].detach().cpu()}
    return outputs, grads, weights


def differences(actual: torch.Tensor, expected: torch.Tensor, rtol: float, atol: float) -> dict[str, float]:
    diff = (actual - expected).abs()
    bad = diff > atol + rtol * expected.abs()
    return {"max_abs": float(diff.max()) if diff.numel() else 0.0,
            "max_ref": float(expected.abs().max()) if expected.numel() else 0.0,
            "outside_tolerance": int(bad.sum()), "numel": expected.numel()}


def compare(name: str, scene: dict, rasterize_mode: str) -> tuple[dict[str, dict[str, float]], torch.Tensor]:
    """Differences of every output and gradient (gsplat CUDA vs cpu) -> rows, and the mask [N] of Gaussians whose
    radii differ between the two in any camera."""
    cpu_out, cpu_grads, weights = render_and_grads(scene, "cpu", "cpu", rasterize_mode)
    cuda_out, cuda_grads, _ = render_and_grads(scene, "cuda", "gsplat", rasterize_mode, weights)
    rows = {}
    for key in ("colors", "alphas"):
        rows[key] = differences(cuda_out[key], cpu_out[key], rtol=0.0, atol=1e-5)
    radii_differ = (cuda_out["radii"] != cpu_out["radii"]).any(dim=-1).any(dim=0)  # [N]
    rows["radii"] = {"max_abs": float((cuda_out["radii"] - cpu_out["radii"]).abs().max()),
                     "outside_tolerance": int(radii_differ.sum()), "numel": int(radii_differ.numel())}
    for key, expected in cpu_grads.items():
        floor = 1e-5 * max(float(expected.abs().max()), 1e-3)
        rows[f"grad_{key}"] = differences(cuda_grads[key], expected, rtol=1e-4, atol=floor)
    REPORT[f"{name}/{rasterize_mode}"] = rows
    path = os.environ.get("KC_PARITY_REPORT")
    if path:
        with open(path, "w") as fh:
            json.dump(REPORT, fh, indent=1)
    return rows, radii_differ


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_random_scene_sh3_matches_cpu_path(rasterize_mode):
    rows, _ = compare("random_sh3", random_scene(), rasterize_mode)
    failing = {k: v for k, v in rows.items() if v["outside_tolerance"]}
    assert not failing, failing


@pytest.mark.parametrize("rasterize_mode", ["classic", "antialiased"])
def test_garden_matches_cpu_path(garden_npz, rasterize_mode):
    """Real points, gsplat's random scales (1e-4 to 2e-2: many needle-thin Gaussians with nearly singular 2D
    covariances). Measured on an H100 (docs/results/gpu/README.md): 1 of 111785 radii differs, 11 (classic) / 26
    (antialiased) of 153090 colour values by up to 5e-5 / 9e-4, and 0.01-0.4 % of each gradient's elements fall
    outside the CPU-vs-reference tolerance. Dropping the Gaussian whose radius differs changes none of that, so the
    cause is per-pixel alpha decisions (the 1/255 cut-off, early termination) flipping under fast-math CUDA for
    ill-conditioned conics. The bounds below hold those measurements with margin; the random scene above is exact."""
    rows, radii_differ = compare("garden_quarter", garden_scene(garden_npz), rasterize_mode)
    assert int(radii_differ.sum()) <= 10, rows["radii"]
    for key, row in rows.items():
        if key == "grad_viewmats":  # 48 sums over every Gaussian: bounded relative to the largest entry
            assert row["max_abs"] <= 5e-4 * row["max_ref"], (key, row)
        else:
            assert row["outside_tolerance"] <= 1e-2 * row["numel"], (key, row)
    assert rows["colors"]["max_abs"] <= 5e-3 and rows["alphas"]["max_abs"] <= 5e-3, rows
