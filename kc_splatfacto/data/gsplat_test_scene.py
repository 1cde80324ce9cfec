"""gsplat's test scene (``test_garden.npz``: a Mip-NeRF 360 garden point cloud and 3 cameras) as Gaussians.

The Gaussians are built as gsplat's ``gsplat/_helper.py:load_test_data`` builds them, so a rasterizer test or
benchmark here renders what gsplat's own tests render: points cropped to [-2, 2]^3 (111,785 of them), random unit
quaternions, scales U[1e-4, 0.02], opacities U[0, 1], colours from the points. Random draws come from a torch
generator with the given seed (gsplat uses torch's global RNG: the draws differ from gsplat's, their
distributions do not).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

# gsplat's crop: points outside [-CROP, CROP]^3 are dropped.
CROP = 2.0
SCALE_RANGE = (1e-4, 0.02)


def load_gsplat_test_scene(path: str | Path, seed: int = 42) -> dict:
    """Gaussians and cameras from gsplat's ``test_garden.npz`` on the CPU.

    Returns ``means`` [N, 3], ``quats`` [N, 4] (unit), ``scales`` [N, 3], ``opacities`` [N], ``colors`` [N, 3] in
    [0, 1], ``viewmats`` [C, 4, 4], ``Ks`` [C, 3, 3] (float32 tensors) and ``width``, ``height`` (ints).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(
            f"gsplat test scene not found: {path} (it is gsplat's assets/test_garden.npz; "
            "the tests and benchmarks look for it in $KC_SHARED_DATA/gsplat-test-garden/)"
        )
    data = np.load(path)
    means = torch.from_numpy(data["means3d"]).float()
    colors = torch.from_numpy(data["colors"] / 255.0).float()
    inside = ((means >= -CROP) & (means <= CROP)).all(dim=-1)
    means, colors = means[inside], colors[inside]
    n = means.shape[0]
    generator = torch.Generator().manual_seed(seed)
    low, high = SCALE_RANGE
    scales = torch.rand(n, 3, generator=generator) * (high - low) + low
    quats = F.normalize(torch.randn(n, 4, generator=generator), dim=-1)
    opacities = torch.rand(n, generator=generator)
    return dict(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=torch.from_numpy(data["viewmats"]).float(),
        Ks=torch.from_numpy(data["Ks"]).float(),
        width=int(data["width"]),
        height=int(data["height"]),
    )
