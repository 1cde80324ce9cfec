"""Measurements of a scene's training split that the scene plan decides from (never the test views).

Each function takes plain tensors (images [H, W, C] uint8 or float in [0, 1], cameras, seed points) and returns
numbers with their meaning in the docstring, so that a test can build a scene whose right answer is known.

- :func:`view_coverage`: the mean fraction of the training views that see a seed point (in front of the camera,
  inside the image). A forward-facing capture sees nearly every point from every view (about 1); a 360-degree
  capture sees each point from a fraction of them.
- :func:`colour_spread`: the view dependence at the seed points: the median over points of the robust spread (median
  absolute deviation) of the colour each training view that sees the point shows there.
- :func:`border_colour`: the share of the images' border pixels near white and near black.
- :func:`detail_levels`: per DWT level, the ground truth's detail RMS over the images' noise floor (Donoho's robust
  MAD estimate on the finest diagonal band), and the coefficient count per band.
- :func:`cross_band_share`: the CBC term's size on the ground truth relative to the wavelet L1 term's.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from kc_splatfacto.data.outputs import Cameras
from kc_splatfacto.losses.frequency import FrequencyLossConfig, covariance_penalty, level_weights
from kc_splatfacto.losses.wavelets import coeff_length, dwt2, filter_length, supported_levels

MAX_POINTS = 20_000
"""seed points measured at most (an evenly strided subset: the statistics are medians and means)"""
NEAR = 1e-3
"""a point this close to a camera's plane (or behind it) is not seen by that view"""
SPREAD_SIDE = 128
"""colours are sampled at about this many pixels on the images' shorter side (box-averaged), so that a seed point's
sub-pixel misregistration does not read as view dependence"""
MIN_VIEWS_FOR_SPREAD = 3
"""a point seen by fewer views has no measurable spread"""
BORDER_FRACTION = 0.02
"""the border is this fraction of each side (at least one pixel)"""
NEAR_EXTREME = 0.06
"""a border pixel is white (black) when every channel is within this of 1 (0)"""
MAD_TO_SIGMA = 0.6745
"""median |x| / 0.6745 estimates a Gaussian's standard deviation (Donoho and Johnstone's noise estimate)"""


def _strided(points: torch.Tensor, limit: int = MAX_POINTS) -> torch.Tensor:
    stride = max(1, -(-len(points) // limit))
    return points[::stride]


def project(points: torch.Tensor, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pixel coordinates of ``points`` [M, 3] in every camera: (u [N, M], v [N, M], seen [N, M] bool: in front of
    the camera and inside its image). OpenCV axes: z forward, u right, v down, pixel centres at +0.5."""
    viewmats = cameras.viewmats.double()
    xyz = points.double()
    cam = torch.einsum("nij,mj->nmi", viewmats[:, :3, :3], xyz) + viewmats[:, None, :3, 3]
    z = cam[..., 2]
    safe = torch.where(z > NEAR, z, torch.ones_like(z))
    Ks = cameras.Ks.double()
    u = Ks[:, None, 0, 0] * cam[..., 0] / safe + Ks[:, None, 0, 2]
    v = Ks[:, None, 1, 1] * cam[..., 1] / safe + Ks[:, None, 1, 2]
    widths = cameras.widths.double()[:, None]
    heights = cameras.heights.double()[:, None]
    seen = (z > NEAR) & (u >= 0) & (u < widths) & (v >= 0) & (v < heights)
    return u, v, seen


FACING_COS = 0.5
"""a view sees a point's surface only if its direction to the point is within 60 degrees (cos 0.5) of the mean
direction of the views that have the point in frame: the surface's normal is unknown, that mean is its best guess,
and a view from further round sees the point's back or an occluder (a 360-degree ring keeps a third of its views)"""


@dataclass(frozen=True)
class Coverage:
    """``views``: training views; ``points``: seed points measured (in frame of at least one view); ``in_frame``:
    the mean over those points of the fraction of views that have each in frame (in front, inside the image);
    ``coverage``: the same fraction counting only the views that face the point (:data:`FACING_COS`; 1: every view
    sees every point, as in a forward-facing capture)."""

    views: int
    points: int
    in_frame: float
    coverage: float


def view_coverage(points: torch.Tensor | None, cameras: Cameras) -> Coverage:
    """How much of the scene each training view sees (see :class:`Coverage`); a scene without seed points counts as
    seen by every view (coverage 1: nothing measured, the schedule then follows the view count alone)."""
    views = len(cameras)
    if points is None or len(points) == 0:
        return Coverage(views, 0, 1.0, 1.0)
    pts = _strided(points.float()).double()
    _, _, seen = project(pts, cameras)
    measured = seen.any(0)
    if not bool(measured.any()):
        return Coverage(views, 0, 1.0, 1.0)
    seen, pts = seen[:, measured], pts[measured]
    centres = cameras.centers().double()  # [N, 3]
    to_camera = centres[:, None, :] - pts[None]  # [N, P, 3]
    to_camera = to_camera / to_camera.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    mean = (to_camera * seen[..., None]).sum(0)
    mean = mean / mean.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    facing = seen & ((to_camera * mean[None]).sum(-1) >= FACING_COS)
    return Coverage(views, int(measured.sum()), float(seen.sum(0).double().mean() / views),
                    float(facing.sum(0).double().mean() / views))


def _as_float(image: torch.Tensor) -> torch.Tensor:
    """[H, W, C] in [0, 1], float32; RGBA composited over black is not wanted here: the alpha is dropped (the
    plan reads colour where the image has it)."""
    image = image[..., :3]
    return image.float() / 255.0 if image.dtype == torch.uint8 else image.float()


def _box(image: torch.Tensor, factor: int) -> torch.Tensor:
    if factor <= 1:
        return image
    return F.avg_pool2d(image.permute(2, 0, 1)[None], factor, factor)[0].permute(1, 2, 0)


@dataclass(frozen=True)
class ColourSpread:
    """``spread``: the median over seed points of the per-point colour spread over the views that see it (median
    absolute deviation, mean over RGB, in 8-bit levels); ``points``: points with at least
    :data:`MIN_VIEWS_FOR_SPREAD` views; ``views_per_point``: their median view count; ``noise``: the spread the
    images' noise alone gives at the scale the colours are sampled (the median |HH| of a one-level Haar transform of
    the sampled images, per channel: an orthonormal band keeps white noise's deviation s, and the median absolute
    deviation of s-noise is 0.6745 s, the same number)."""

    spread: float
    points: int
    views_per_point: float
    noise: float = float("nan")


def colour_spread(images: Sequence[torch.Tensor], cameras: Cameras, points: torch.Tensor | None) -> ColourSpread:
    """The view dependence of the scene's colour at its seed points (:class:`ColourSpread`): a Lambertian surface
    shows one colour in every view (spread at the noise), a specular or view-dependent one a spread of colours. The
    median over views (MAD) keeps an occluder seen in a minority of the views from counting. No seed points: NaN."""
    if points is None or len(points) == 0:
        return ColourSpread(float("nan"), 0, 0.0)
    pts = _strided(points.float())
    u, v, seen = project(pts, cameras)
    colours = torch.full((len(cameras), len(pts), 3), float("nan"), dtype=torch.float32)
    noise = []
    for i, image in enumerate(images):
        height, width = image.shape[:2]
        factor = max(1, min(height, width) // SPREAD_SIDE)
        small = _box(_as_float(image), factor)
        noise.append(_haar_diagonal_mad(small))
        sh, sw = small.shape[:2]
        col = (u[i] / factor).floor().long().clamp(0, sw - 1)
        row = (v[i] / factor).floor().long().clamp(0, sh - 1)
        mask = seen[i] & ((u[i] / factor) < sw) & ((v[i] / factor) < sh)
        colours[i, mask] = small[row[mask], col[mask]]
    counts = (~torch.isnan(colours[..., 0])).sum(0)
    keep = counts >= MIN_VIEWS_FOR_SPREAD
    floor = float(torch.tensor(noise).median()) * 255.0
    if not bool(keep.any()):
        return ColourSpread(float("nan"), 0, 0.0, floor)
    kept = colours[:, keep]  # [N, P, 3]
    centre = torch.nanmedian(kept, dim=0).values
    mad = torch.nanmedian((kept - centre).abs(), dim=0).values  # [P, 3]
    per_point = mad.mean(-1) * 255.0
    return ColourSpread(float(per_point.median()), int(keep.sum()), float(counts[keep].float().median()), floor)


def _haar_diagonal_mad(image: torch.Tensor) -> float:
    """median |HH| of a one-level orthonormal Haar transform of image [H, W, 3] in [0, 1], the mean over channels:
    0.6745 times the deviation of the image's white noise (Donoho's estimate; edges are a minority of the band)."""
    height, width = (image.shape[0] // 2) * 2, (image.shape[1] // 2) * 2
    if height == 0 or width == 0:
        return float("nan")
    x = image[:height, :width].double()
    diagonal = (x[0::2, 0::2] - x[0::2, 1::2] - x[1::2, 0::2] + x[1::2, 1::2]) / 2.0
    return float(diagonal.abs().flatten(0, 1).median(dim=0).values.mean())


@dataclass(frozen=True)
class Border:
    """Shares of the training images' border pixels that are near white and near black (:data:`NEAR_EXTREME`)."""

    white: float
    black: float


def border_colour(images: Sequence[torch.Tensor]) -> Border:
    """What the border of the training images holds (:class:`Border`): an object shot on a white (black) backdrop
    has nearly all of it white (black)."""
    white = black = total = 0
    for image in images:
        rgb = _as_float(image)
        height, width = rgb.shape[:2]
        by, bx = max(1, int(height * BORDER_FRACTION)), max(1, int(width * BORDER_FRACTION))
        frame = torch.ones(height, width, dtype=torch.bool)
        frame[by:height - by, bx:width - bx] = False
        pixels = rgb[frame]
        white += int((pixels >= 1.0 - NEAR_EXTREME).all(-1).sum())
        black += int((pixels <= NEAR_EXTREME).all(-1).sum())
        total += len(pixels)
    return Border(white / max(total, 1), black / max(total, 1))


def _gray(image: torch.Tensor) -> torch.Tensor:
    return _as_float(image).mean(-1)


@dataclass(frozen=True)
class DetailLevels:
    """Per DWT level j = 1 (finest) .. J of the images at ``height`` x ``width`` (the smallest training image,
    downscaled by the warm-up's first stage ``downscale``): ``snr[j-1]``, the ground truth's detail RMS (the three
    bands) over the noise floor ``noise`` (8-bit levels, estimated on the full-size finest diagonal band);
    ``coefficients[j-1]``, the coefficients of one band of one image and channel at the first stage."""

    noise: float
    snr: tuple[float, ...]
    coefficients: tuple[int, ...]
    height: int
    width: int
    downscale: int


def detail_levels(images: Sequence[torch.Tensor], wave: str, levels: int, downscale: int = 1) -> DetailLevels:
    """The detail each DWT level of the training images holds against their own noise (:class:`DetailLevels`). A
    white-noise image of standard deviation s has coefficients of standard deviation s in every band of an orthogonal
    wavelet, so a level whose RMS is near the noise estimate supervises noise."""
    noise: list[float] = []
    energies: list[list[float]] = []
    for image in images:
        gray = _gray(image)[None, None].double()
        coeffs = dwt2(gray, wave, levels, warn=False)
        if not coeffs.details:
            continue
        diagonal = coeffs.details[0][0, 0, 2]
        noise.append(float(diagonal.abs().median() / MAD_TO_SIGMA))
        energies.append([float(band[0, 0].pow(2).mean().sqrt()) for band in coeffs.details])
    height = min(int(image.shape[0]) for image in images)
    width = min(int(image.shape[1]) for image in images)
    stage_h, stage_w = max(1, height >> downscale), max(1, width >> downscale)
    kept = supported_levels(stage_h, stage_w, wave, levels)
    coefficients = []
    h, w = stage_h, stage_w
    flen = filter_length(wave)
    for _ in range(kept):
        h, w = coeff_length(h, flen, "symmetric"), coeff_length(w, flen, "symmetric")
        coefficients.append(h * w)
    sigma = float(torch.tensor(noise).median()) if noise else float("nan")
    depth = min((len(e) for e in energies), default=0)
    snr = tuple(float(torch.tensor([e[j] for e in energies]).median()) / max(sigma, 1e-12) for j in range(depth))
    return DetailLevels(sigma * 255.0, snr, tuple(coefficients), height, width, downscale)


def cross_band_share(images: Sequence[torch.Tensor], frequency: FrequencyLossConfig) -> float:
    """The CBC term against the wavelet L1 on the ground truth: cbc_weight x L_cov(gt) over wavelet_weight x
    sum_j w_j sum_o mean|c^j_o(gt)|, the median over the images. Early in training the render lacks the detail, so each
    term is about its ground-truth value: the ratio is how much the CBC can add to what the wavelet term asks.
    No wavelet term: inf when the CBC has a weight (it is then the only detail term), 0 when it has none."""
    if frequency.cbc_weight <= 0:
        return 0.0
    if frequency.wavelet_weight <= 0:
        return float("inf")
    shares = []
    for image in images:
        rgb = _as_float(image).permute(2, 0, 1)[None]
        coeffs = dwt2(rgb, frequency.wave, frequency.wavelet_levels, frequency.wavelet_mode, warn=False)
        if not coeffs.details:
            continue
        weights = level_weights(len(coeffs.details), frequency.wavelet_weighting)
        wavelet = sum(3.0 * w * float(band.abs().mean()) for w, band in zip(weights, coeffs.details))  # as wavelet_l1
        cov = float(covariance_penalty(coeffs, correlation=frequency.cbc_correlation).mean())  # as cbc_loss
        shares.append(frequency.cbc_weight * cov / max(frequency.wavelet_weight * wavelet, 1e-30))
    return float(torch.tensor(shares).median()) if shares else 0.0
