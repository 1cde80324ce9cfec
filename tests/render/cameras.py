"""Camera rigs shared by the render tests."""

from __future__ import annotations

import math

import torch


def turning_viewmats(n_cameras: int, angle_step: float) -> torch.Tensor:
    """[C, 4, 4] world-to-camera matrices: camera c turned by ``c * angle_step`` radians about y and shifted by
    (0.1, -0.05, 0.2) * c, so the cameras see the same scene from slightly different places."""
    viewmats = torch.eye(4).repeat(n_cameras, 1, 1)
    for c in range(n_cameras):
        angle = angle_step * c
        viewmats[c, :3, :3] = torch.tensor([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0],
                                            [-math.sin(angle), 0, math.cos(angle)]])
        viewmats[c, :3, 3] = torch.tensor([0.1 * c, -0.05 * c, 0.2 * c])
    return viewmats
