"""Reference tiled compositing in plain torch: slow, obviously correct, differentiable by autograd.

It follows gsplat 1.5.3's ``rasterize_to_pixels`` forward kernel step by step, one tile at a time: the tile's
Gaussians in their sorted (front-to-back) order, every pixel centre ``(j + 0.5, i + 0.5)`` of the tile,

    sigma = 0.5 * (a dx^2 + c dy^2) + b dx dy,    (dx, dy) = mean2d - pixel centre,  conic = (a, b, c)
    alpha = min(0.999, opacity * exp(-sigma)),    skipped when sigma < 0 or alpha < 1/255,
    a Gaussian is composited only while T * (1 - alpha) > 1e-4 (the pixel stops BEFORE T would reach 1e-4),
    colour = sum_k c_k alpha_k T_k + T_final * background,   render_alpha = 1 - T_final.

The sequential loop becomes: alpha of skipped Gaussians set to 0, ``T_after = cumprod(1 - alpha)`` (T never
increases, so once it has dropped to <= 1e-4 it stays there: the first such Gaussian and every later one are
excluded), then the exclusive cumulative product of the kept ``1 - alpha`` gives each Gaussian's T. The keep/skip
decisions are constants for autograd, exactly as the CUDA backward replays the forward's decisions.
It is the oracle of the compiled CPU path (``rasterize_cpu.py``) and of the gradient tests.
"""

from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from .constants import ALPHA_CLAMP, ALPHA_THRESHOLD, PIXEL_CENTER_OFFSET, TRANSMITTANCE_MIN


def composite_pixels(
    pixels: Tensor, means2d: Tensor, conics: Tensor, colors: Tensor, opacities: Tensor
) -> tuple[Tensor, Tensor]:
    """Front-to-back compositing of K depth-sorted Gaussians at P pixel centres (no background).

    Args:
        pixels: [P, 2] pixel centres (x, y).
        means2d: [P, K, 2] or [K, 2]; conics: [K, 3]; colors: [K, D]; opacities: [K]; all in front-to-back order.

    Returns:
        colors [P, D] and transmittance after the last composited Gaussian [P].
    """
    delta = means2d - pixels[:, None, :]  # [P, K, 2]
    dx, dy = delta[..., 0], delta[..., 1]
    a, b, c = conics[:, 0], conics[:, 1], conics[:, 2]
    sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy  # [P, K]
    alpha = torch.clamp_max(opacities * torch.exp(-sigma), ALPHA_CLAMP)
    with torch.no_grad():
        used = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
        t_after = torch.cumprod(1.0 - torch.where(used, alpha, torch.zeros_like(alpha)), dim=-1)
        used &= t_after > TRANSMITTANCE_MIN
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))
    one_minus = 1.0 - alpha
    trans = torch.cumprod(one_minus, dim=-1)  # T after each Gaussian
    trans_before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=-1)
    weights = alpha * trans_before  # [P, K]
    return weights @ colors, trans[:, -1]


def _capture_abs(grad: Tensor, store: Tensor, index: Tensor) -> None:
    """Add sum over pixels of |d loss / d mean2d| (per pixel, per axis) into ``store`` at ``index`` (gsplat absgrad)."""
    store.index_add_(0, index, grad.abs().sum(dim=0).to(store.dtype))


def rasterize_to_pixels_torch(
    means2d: Tensor,
    conics: Tensor,
    colors: Tensor,
    opacities: Tensor,
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,
    flatten_ids: Tensor,
    backgrounds: Optional[Tensor] = None,
    absgrad: bool = False,
) -> tuple[Tensor, Tensor]:
    """Rasterize projected Gaussians tile by tile (reference for ``rasterize_to_pixels_cpu``).

    Args:
        means2d: [C, N, 2]; conics: [C, N, 3]; colors: [C, N, D]; opacities: [C, N].
        image_width, image_height: pixels; tile_size: pixels per tile side.
        isect_offsets: [C, tile_height, tile_width] int32 from ``isect_offset_encode``.
        flatten_ids: [M] indices into the flattened [C * N], sorted by camera, tile, depth.
        backgrounds: [C, D] or None (black).
        absgrad: also accumulate ``means2d.absgrad`` [C, N, 2] (sum over pixels of the absolute per-pixel gradient)
            during backward; ``means2d`` must require grad.

    Returns:
        render_colors [C, H, W, D] and render_alphas [C, H, W, 1].
    """
    n_cameras, n_gauss, channels = colors.shape
    tile_height, tile_width = isect_offsets.shape[-2:]
    device, dtype = means2d.device, means2d.dtype
    n_isects = flatten_ids.numel()
    offsets = isect_offsets.reshape(-1).to(torch.int64).tolist() + [n_isects]
    flat_ids = flatten_ids.to(torch.int64)

    abs_store = None
    if absgrad:
        if not means2d.requires_grad:
            raise ValueError("absgrad=True needs means2d that requires grad")
        abs_store = torch.zeros((n_cameras * n_gauss, 2), dtype=dtype, device=device)
        # gsplat's contract: the attribute on meta["means2d"] itself, filled by the hooks during backward
        means2d.absgrad = abs_store.view(n_cameras, n_gauss, 2)  # type: ignore[attr-defined]

    means2d_flat = means2d.reshape(-1, 2)
    conics_flat = conics.reshape(-1, 3)
    colors_flat = colors.reshape(-1, channels)
    opacities_flat = opacities.reshape(-1)

    local = torch.arange(tile_size, device=device, dtype=dtype)
    local_y, local_x = torch.meshgrid(local, local, indexing="ij")
    local_pixels = torch.stack([local_x.reshape(-1), local_y.reshape(-1)], dim=-1) + PIXEL_CENTER_OFFSET  # [P, 2]

    tiles_colors, tiles_trans = [], []
    for cam in range(n_cameras):
        background = backgrounds[cam] if backgrounds is not None else None
        for ty in range(tile_height):
            for tx in range(tile_width):
                tile = (cam * tile_height + ty) * tile_width + tx
                start, end = offsets[tile], offsets[tile + 1]
                if end <= start:
                    tile_color = torch.zeros((tile_size * tile_size, channels), dtype=dtype, device=device)
                    tile_trans = torch.ones((tile_size * tile_size,), dtype=dtype, device=device)
                else:
                    ids = flat_ids[start:end]
                    pixels = local_pixels + torch.tensor([tx * tile_size, ty * tile_size], dtype=dtype, device=device)
                    xy = means2d_flat[ids]
                    if abs_store is not None:
                        # One copy of the means per pixel, so the hook sees each pixel's gradient separately.
                        xy = xy.unsqueeze(0).expand(pixels.shape[0], -1, -1)
                        if xy.requires_grad:
                            xy.register_hook(lambda g, ids=ids: _capture_abs(g, abs_store, ids))
                    tile_inputs = (pixels, xy, conics_flat[ids], colors_flat[ids], opacities_flat[ids])
                    if torch.is_grad_enabled() and any(t.requires_grad for t in tile_inputs):
                        # Recompute the tile in backward instead of keeping its [pixels x Gaussians] intermediates:
                        # the graph of a whole image would otherwise hold gigabytes (same ops, same gradients).
                        tile_color, tile_trans = checkpoint(composite_pixels, *tile_inputs, use_reentrant=False)
                    else:
                        tile_color, tile_trans = composite_pixels(*tile_inputs)
                if background is not None:
                    tile_color = tile_color + tile_trans[:, None] * background
                tiles_colors.append(tile_color)
                tiles_trans.append(tile_trans)

    def assemble(tiles: list[Tensor], depth: int) -> Tensor:
        stacked = torch.stack(tiles).reshape(n_cameras, tile_height, tile_width, tile_size, tile_size, depth)
        image = stacked.permute(0, 1, 3, 2, 4, 5).reshape(
            n_cameras, tile_height * tile_size, tile_width * tile_size, depth
        )
        return image[:, :image_height, :image_width]

    if not tiles_colors:  # zero cameras
        return (
            torch.zeros((n_cameras, image_height, image_width, channels), dtype=dtype, device=device),
            torch.zeros((n_cameras, image_height, image_width, 1), dtype=dtype, device=device),
        )
    render_colors = assemble(tiles_colors, channels)
    render_alphas = 1.0 - assemble([t[:, None] for t in tiles_trans], 1)
    return render_colors, render_alphas
