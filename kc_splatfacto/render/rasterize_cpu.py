"""Fast CPU rasterizer: gsplat 1.5.3's ``rasterize_to_pixels`` with hand-written forward and backward (numba).

Same signature and semantics as ``rasterize_to_pixels_torch`` (the reference oracle) and gsplat's CUDA kernels
``RasterizeToPixels3DGSFwd.cu`` / ``RasterizeToPixels3DGSBwd.cu``: pixel centres at +0.5, front-to-back
compositing of the depth-sorted intersections of each 16 px tile, ``alpha = min(ALPHA_CLAMP, o * exp(-sigma))``,
skip ``sigma < 0`` and ``alpha < ALPHA_THRESHOLD``, stop before the transmittance would fall to the threshold,
background blended with the final transmittance; backward in reverse order from each pixel's last contributor.

Parallel over (camera, tile); each intersection's gradient is written by the one tile that owns it and then
reduced to Gaussians in a fixed order, so results do not depend on the thread count. 16 px tiles run the
vectorized 16-lane kernels (float32 like gsplat, per-intersection gradient totals and the reduction to Gaussians
in float64); other tile sizes run scalar kernels (float64 transmittance and gradient sums in backward).
See ``docs/rasterizer.md`` (Fast CPU path and benchmark).
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from torch import Tensor

from . import _cpu_kernels as K
from .constants import ALPHA_CLAMP, ALPHA_THRESHOLD, BLOCK_TILE_SIZE, PIXEL_CENTER_OFFSET, TRANSMITTANCE_MIN

__all__ = ["rasterize_to_pixels_cpu"]

# Tiles handed to a thread at a time: small chunks balance tiles of very different cost (dense centre, empty sky)
# dynamically; the results do not depend on the schedule.
TILES_PER_CHUNK = 4


def _np32(x: Tensor) -> np.ndarray:
    return np.ascontiguousarray(x.detach().to(device="cpu", dtype=torch.float32).numpy())


def _check_inputs(means2d, conics, colors, opacities, image_width, image_height, tile_size, isect_offsets,
                  flatten_ids, backgrounds) -> None:
    if means2d.dim() != 3 or means2d.shape[-1] != 2:
        raise ValueError(f"means2d must be [C, N, 2], got {tuple(means2d.shape)}")
    C, N = means2d.shape[:2]
    if conics.shape != (C, N, 3):
        raise ValueError(f"conics must be [C, N, 3] = {(C, N, 3)}, got {tuple(conics.shape)}")
    if colors.dim() != 3 or colors.shape[:2] != (C, N) or colors.shape[-1] < 1:
        raise ValueError(f"colors must be [C, N, D] with C, N = {(C, N)}, got {tuple(colors.shape)}")
    if opacities.shape != (C, N):
        raise ValueError(f"opacities must be [C, N] = {(C, N)}, got {tuple(opacities.shape)}")
    if image_width < 1 or image_height < 1 or tile_size < 1:
        raise ValueError(f"image size and tile size must be positive, got {image_width}x{image_height}, "
                         f"tile_size={tile_size}")
    tile_h = (image_height + tile_size - 1) // tile_size
    tile_w = (image_width + tile_size - 1) // tile_size
    if isect_offsets.shape != (C, tile_h, tile_w):
        raise ValueError(f"isect_offsets must be [C, tile_h, tile_w] = {(C, tile_h, tile_w)} for a "
                         f"{image_width}x{image_height} image and tile_size {tile_size}, "
                         f"got {tuple(isect_offsets.shape)}")
    if flatten_ids.dim() != 1:
        raise ValueError(f"flatten_ids must be [M], got {tuple(flatten_ids.shape)}")
    if backgrounds is not None and backgrounds.shape != (C, colors.shape[-1]):
        raise ValueError(f"backgrounds must be [C, D] = {(C, colors.shape[-1])}, got {tuple(backgrounds.shape)}")
    for name, t in (("means2d", means2d), ("conics", conics), ("colors", colors), ("opacities", opacities)):
        if t.device.type != "cpu":
            raise ValueError(f"rasterize_to_pixels_cpu needs CPU tensors, {name} is on {t.device}; "
                             "use rasterizer='gsplat' for CUDA tensors")


def _constants() -> tuple[np.float32, np.float32, np.float32, np.float32]:
    # float32 scalars keep the kernels' arithmetic in float32, as gsplat's (and the reference's) is
    return (np.float32(PIXEL_CENTER_OFFSET), np.float32(ALPHA_CLAMP), np.float32(ALPHA_THRESHOLD),
            np.float32(TRANSMITTANCE_MIN))


class _RasterizeToPixelsCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, backgrounds, image_width, image_height, tile_size,
                isect_offsets, flatten_ids, absgrad):
        C, N = means2d.shape[:2]
        D = colors.shape[-1]
        tile_h, tile_w = isect_offsets.shape[-2:]
        pixel_offset, max_alpha, alpha_threshold, transmittance_threshold = _constants()

        ids = np.ascontiguousarray(flatten_ids.detach().cpu().numpy(), dtype=np.int32)
        offsets = np.ascontiguousarray(isect_offsets.detach().cpu().numpy(), dtype=np.int32).reshape(-1)
        bg = np.zeros((C, D), np.float32) if backgrounds is None else _np32(backgrounds)

        packed = np.empty((ids.shape[0], K.PACK_HEAD + D), np.float32)
        K.pack_isects(_np32(means2d).reshape(C * N, 2), _np32(conics).reshape(C * N, 3),
                      _np32(opacities).reshape(C * N), _np32(colors).reshape(C * N, D), ids, alpha_threshold,
                      packed)
        render_colors = np.empty((C, image_height, image_width, D), np.float32)
        T_final = np.empty((C, image_height, image_width), np.float32)
        last_ids = np.empty((C, image_height, image_width), np.int32)
        n_contrib = np.empty((C, image_height, image_width), np.int32)
        with numba.parallel_chunksize(TILES_PER_CHUNK):
            if tile_size == BLOCK_TILE_SIZE:
                K.rasterize_fwd_blocks(packed, offsets, bg, C, image_height, image_width, tile_h, tile_w, pixel_offset,
                                       max_alpha, alpha_threshold, transmittance_threshold, render_colors, T_final,
                                       last_ids, n_contrib)
            else:
                K.rasterize_fwd(packed, offsets, bg, C, image_height, image_width, tile_size, tile_h, tile_w,
                                pixel_offset, max_alpha, alpha_threshold, transmittance_threshold, render_colors,
                                T_final, last_ids, n_contrib)

        ctx.geometry = (C, N, D, image_width, image_height, tile_size, tile_h, tile_w)
        ctx.arrays = (packed, offsets, ids, bg, T_final, last_ids)
        ctx.has_backgrounds = backgrounds is not None
        ctx.absgrad = absgrad
        # gsplat sets ``.absgrad`` on this very object (meta["means2d"]), so keep the Python reference
        ctx.means2d = means2d
        # composited (pixel, Gaussian) pairs of the last forward pass, for benchmarks
        rasterize_to_pixels_cpu.last_contributing_pairs = int(n_contrib.sum(dtype=np.int64))
        dtype = means2d.dtype
        out_colors = torch.from_numpy(render_colors).to(dtype)
        out_alphas = torch.from_numpy(1.0 - T_final).unsqueeze(-1).to(dtype)
        return out_colors, out_alphas

    @staticmethod
    def backward(ctx, v_render_colors, v_render_alphas):
        C, N, D, image_width, image_height, tile_size, tile_h, tile_w = ctx.geometry
        packed, offsets, ids, bg, T_final, last_ids = ctx.arrays
        pixel_offset, max_alpha, alpha_threshold, _ = _constants()
        v_colors_out = (np.zeros((C, image_height, image_width, D), np.float32) if v_render_colors is None
                        else _np32(v_render_colors))
        v_alphas_out = (np.zeros((C, image_height, image_width), np.float32) if v_render_alphas is None
                        else _np32(v_render_alphas).reshape(C, image_height, image_width))

        isect_grads = np.zeros((ids.shape[0], K.GRAD_HEAD + D), np.float32)
        with numba.parallel_chunksize(TILES_PER_CHUNK):
            if tile_size == BLOCK_TILE_SIZE:
                K.rasterize_bwd_blocks(packed, offsets, bg, T_final, last_ids, v_colors_out, v_alphas_out, C,
                                       image_height, image_width, tile_h, tile_w, pixel_offset, max_alpha,
                                       alpha_threshold, isect_grads)
            else:
                K.rasterize_bwd(packed, offsets, bg, T_final, last_ids, v_colors_out, v_alphas_out, C, image_height,
                                image_width, tile_size, tile_h, tile_w, pixel_offset, max_alpha, alpha_threshold,
                                isect_grads)
        dtype = ctx.means2d.dtype
        # rounded once from the float64 sums into the inputs' dtype (float32 for the other float dtypes)
        out = dtype if dtype in (torch.float32, torch.float64) else torch.float32
        v_means2d = torch.empty(C, N, 2, dtype=out)
        v_conics = torch.empty(C, N, 3, dtype=out)
        v_opacities = torch.empty(C, N, dtype=out)
        v_colors = torch.empty(C, N, D, dtype=out)
        v_abs = torch.empty(C, N, 2, dtype=out) if ctx.absgrad else torch.empty(0, 2, dtype=out)
        K.reduce_isect_grads(isect_grads, ids, max(1, numba.get_num_threads()),
                             np.zeros((C * N, K.GRAD_HEAD + D), np.float64),
                             v_means2d.numpy().reshape(C * N, 2), v_conics.numpy().reshape(C * N, 3),
                             v_opacities.numpy().reshape(C * N), v_abs.numpy().reshape(-1, 2),
                             v_colors.numpy().reshape(C * N, D))
        if out != dtype:
            v_means2d, v_conics, v_opacities, v_colors, v_abs = (
                t.to(dtype) for t in (v_means2d, v_conics, v_opacities, v_colors, v_abs))
        if ctx.absgrad:
            ctx.means2d.absgrad = v_abs
        v_backgrounds = None
        if ctx.has_backgrounds and ctx.needs_input_grad[4]:
            # d(out)/d(bg) = T_final per pixel
            v_backgrounds = torch.from_numpy(
                np.einsum("chwd,chw->cd", v_colors_out.astype(np.float64), T_final.astype(np.float64))
            ).to(dtype)
        return v_means2d, v_conics, v_colors, v_opacities, v_backgrounds, None, None, None, None, None, None


def rasterize_to_pixels_cpu(
    means2d: Tensor,  # [C, N, 2]
    conics: Tensor,  # [C, N, 3]
    colors: Tensor,  # [C, N, D]
    opacities: Tensor,  # [C, N]
    image_width: int,
    image_height: int,
    tile_size: int,
    isect_offsets: Tensor,  # [C, tile_h, tile_w] int32
    flatten_ids: Tensor,  # [M] int32/int64, indices into C*N
    backgrounds: Tensor | None = None,  # [C, D]
    absgrad: bool = False,
) -> tuple[Tensor, Tensor]:
    """Rasterize depth-sorted tile intersections to pixels on the CPU (numba), differentiable.

    Returns ``render_colors [C, H, W, D]`` and ``render_alphas [C, H, W, 1]``. Gradients flow to means2d,
    conics, colors, opacities and backgrounds; with ``absgrad=True`` the backward pass also stores the per-pixel
    sum of ``|dL/dmeans2d|`` in ``means2d.absgrad [C, N, 2]`` as gsplat does. Inputs of any float dtype are
    computed in float32 and returned in their dtype.
    """
    _check_inputs(means2d, conics, colors, opacities, image_width, image_height, tile_size, isect_offsets,
                  flatten_ids, backgrounds)
    return _RasterizeToPixelsCPU.apply(means2d, conics, colors, opacities, backgrounds, int(image_width),
                                       int(image_height), int(tile_size), isect_offsets, flatten_ids,
                                       bool(absgrad))
