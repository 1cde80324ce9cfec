"""Every numeric constant of gsplat 1.5.3's projection, tiling, compositing and SH, named once.

Sources (gsplat 1.5.3, ``gsplat/cuda/csrc``): ``Common.h`` / ``Utils.cuh`` (``ALPHA_THRESHOLD``, ``MAX_ALPHA``,
``TRANSMITTANCE_THRESHOLD``, ``persp_proj``), ``ProjectionEWA3DGSFused.cu`` (opacity-aware extent 3.33),
``RasterizeToPixels3DGSFwd.cu`` (pixel centres, compositing), ``SphericalHarmonicsCUDA.cu`` (SH constants),
``gsplat/rendering.py`` (tile size 16, eps2d 0.3, near/far planes, SH colour offset 0.5).
The fast path (``rasterize_cpu.py``) imports these names; it never repeats the numbers.
"""

from __future__ import annotations

# --- compositing (RasterizeToPixels3DGSFwd.cu) ---------------------------------------------------------------------
# alpha = min(ALPHA_CLAMP, opacity * exp(-sigma)); alpha == 1 would make the transmittance exactly 0 and the
# backward division by (1 - alpha) undefined, hence the clamp.
ALPHA_CLAMP = 0.999
# A Gaussian whose alpha at a pixel is below 1/255 (one 8-bit quantum) is skipped there; the same threshold culls
# Gaussians whose (compensated) opacity is below it in the projection.
ALPHA_THRESHOLD = 1.0 / 255.0
# Compositing stops BEFORE the Gaussian that would bring the transmittance T to <= 1e-4 (that Gaussian is excluded).
TRANSMITTANCE_MIN = 1e-4
# Pixel (i, j) is sampled at (j + 0.5, i + 0.5): pixel centres, in the same coordinates as K's cx, cy.
PIXEL_CENTER_OFFSET = 0.5

# --- projection (ProjectionEWA3DGSFused.cu, Utils.cuh) --------------------------------------------------------------
# Screen-space dilation added to the 2D covariance diagonal (the low-pass filter of EWA splatting).
EPS2D = 0.3
NEAR_PLANE = 0.01
FAR_PLANE = 1e10
# The Jacobian's x/z and y/z are clamped to the image's half-extent plus FOV_CLAMP_MARGIN * tan(fov/2) on each side,
# i.e. 1.3x the frustum for a centred principal point, so far off-screen Gaussians do not blow up.
FOV_CLAMP_MARGIN = 0.3
# Radius extent in standard deviations, before the opacity-aware tightening
# extent = min(EXTENT_SIGMA, sqrt(2 * log(opacity / ALPHA_THRESHOLD))) (arXiv 2402.00525, Sec. B.2).
EXTENT_SIGMA = 3.33

# --- tiles (IntersectTile.cu, rendering.py) -------------------------------------------------------------------------
TILE_SIZE = 16
# The fast CPU path's vectorized kernels (render/_cpu_kernels.py) run for tiles of BLOCK_TILE_SIZE px only (other
# tile sizes take its scalar kernels): a tile is BLOCKS_PER_TILE blocks of BLOCK_SIZE x BLOCK_SIZE pixels, and the
# LANES pixels of one block are processed as branch-free SIMD lanes. The block count is a compile-time constant on
# purpose: with a run-time count the forward kernel ran 2.2x slower (docs/rasterizer.md, "Two compositing families").
BLOCK_TILE_SIZE = 16
BLOCK_SIZE = 4
LANES = BLOCK_SIZE * BLOCK_SIZE
BLOCKS_PER_TILE = (BLOCK_TILE_SIZE // BLOCK_SIZE) ** 2
# isect id = camera id << (DEPTH_BITS + tile_n_bits) | tile id << DEPTH_BITS | float32 bits of the depth.
DEPTH_BITS = 32
# camera bits + tile bits must fit in the upper 32 bits of the int64 key.
ISECT_KEY_HIGH_BITS = 32

# --- spherical harmonics (SphericalHarmonicsCUDA.cu, Sloan 2013 "Efficient SH evaluation") ---------------------------
SH_MAX_DEGREE = 3
# Colours from SH are shifted by +0.5 and clamped at 0 ("apple-to-apple with Inria's CUDA backend").
SH_COLOR_OFFSET = 0.5
# 1 / (2 sqrt(pi)) as gsplat writes it: one float64 ulp below the correctly rounded value, the same float32 (the
# compiled projection evaluates SH in float64, so this literal is part of the frozen numerics).
SH_C0 = 0.2820947917738781
SH_C1 = 0.48860251190292
SH_C2 = (
    1.092548430592079,  # xy, yz, xz
    0.9461746957575601,  # z^2 term of m=0
    0.3153915652525201,  # constant of m=0
    0.5462742152960395,  # x^2 - y^2
)
SH_C3 = (
    0.5900435899266435,  # m = +-3
    1.445305721320277,  # m = +-2
    2.285228997322329,  # m = +-1, z^2 coefficient
    0.4570457994644658,  # m = +-1, constant
    1.865881662950577,  # m = 0, z^3 coefficient
    1.119528997770346,  # m = 0, z coefficient
)

# --- expected depth (rendering.py) ----------------------------------------------------------------------------------
# "ED" divides the accumulated depth by the accumulated alpha clamped at this floor.
EXPECTED_DEPTH_ALPHA_MIN = 1e-10
