"""Synthetic scenes whose right plan is known: cameras looking at seed points, images drawn from the points."""

from __future__ import annotations

import math

import numpy as np
import torch

from kc_splatfacto.data.outputs import Cameras

WIDTH, HEIGHT, FOCAL = 96, 64, 80.0


def look_at(centre, target) -> np.ndarray:
    """[4, 4] world-to-camera (OpenCV: x right, y down, z forward) of a camera at ``centre`` looking at ``target``,
    world z up."""
    centre, target = np.asarray(centre, float), np.asarray(target, float)
    forward = (target - centre) / np.linalg.norm(target - centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation
    viewmat[:3, 3] = -rotation @ centre
    return viewmat


def cameras(viewmats, width=WIDTH, height=HEIGHT, focal=FOCAL) -> Cameras:
    n = len(viewmats)
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float32)
    return Cameras(torch.tensor(np.stack(viewmats), dtype=torch.float32), K.expand(n, 3, 3).clone(),
                   torch.full((n,), width, dtype=torch.int64), torch.full((n,), height, dtype=torch.int64))


def forward_facing(views: int) -> tuple[Cameras, torch.Tensor]:
    """``views`` cameras on a small patch of the plane y = 0, all looking along +y at a wall of points at y = 10
    that every view holds in frame (an LLFF-like capture)."""
    side = math.ceil(math.sqrt(views))
    centres = [(0.1 * (i % side), 0.0, 0.1 * (i // side)) for i in range(views)]
    mats = [look_at(c, (c[0], 10.0, c[2])) for c in centres]
    xs, zs = np.meshgrid(np.linspace(-2, 2, 10), np.linspace(-1.5, 1.5, 7))  # 3x3 squares apart
    points = np.stack([xs.ravel(), np.full(xs.size, 10.0), zs.ravel()], 1)
    return cameras(mats), torch.tensor(points, dtype=torch.float32)


def ring(views: int) -> tuple[Cameras, torch.Tensor]:
    """``views`` cameras on a ring of radius 6 round a ball of points of radius 1 at the origin (a 360-degree
    object capture): each point is in every frame, but faced only by the views on its side."""
    mats = [look_at((6 * math.cos(a), 6 * math.sin(a), 0.0), (0, 0, 0))
            for a in np.linspace(0, 2 * math.pi, views, endpoint=False)]
    rng = np.random.default_rng(0)
    points = rng.normal(size=(800, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    points[:, 2] *= 0.5  # within the ring's vertical field of view
    return cameras(mats), torch.tensor(points, dtype=torch.float32)


def draw(cams: Cameras, points: torch.Tensor, colours: np.ndarray, background: np.ndarray) -> list[torch.Tensor]:
    """Each view's image [H, W, 3] uint8: ``background`` [H, W, 3] with every point a 3x3 square of its colour in
    that view (``colours`` [N, M, 3] in [0, 1]), nearer points drawn last."""
    images = []
    for i in range(len(cams)):
        image = background.copy()
        R, t = cams.viewmats[i, :3, :3].double().numpy(), cams.viewmats[i, :3, 3].double().numpy()
        cam = points.double().numpy() @ R.T + t
        order = np.argsort(-cam[:, 2])
        for m in order:
            x, y, z = cam[m]
            if z <= 0:
                continue
            u, v = int(FOCAL * x / z + WIDTH / 2), int(FOCAL * y / z + HEIGHT / 2)
            if 1 <= u < WIDTH - 1 and 1 <= v < HEIGHT - 1:
                image[v - 1:v + 2, u - 1:u + 2] = colours[i, m]
        images.append(torch.tensor(np.round(image * 255), dtype=torch.uint8))
    return images


def texture(seed: int = 0) -> np.ndarray:
    """[H, W, 3] in [0, 1]: a smooth random texture (no constant border)."""
    rng = np.random.default_rng(seed)
    coarse = rng.uniform(0.2, 0.8, size=(HEIGHT // 8 + 1, WIDTH // 8 + 1, 3))
    return np.kron(coarse, np.ones((8, 8, 1)))[:HEIGHT, :WIDTH]
