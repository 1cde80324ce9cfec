"""The Gaussians as a splat file: ``ply``, ``splat``, ``ply-compressed`` or ``spz``.

- ``ply``: Inria's 3DGS PLY (every parameter as float32; what training tools and most viewers read).
- ``splat``: antimatter15's 32-byte records (position, linear scale, RGBA, quaternion in bytes; no view-dependent
  colour), for that viewer and its descendants.
- ``ply-compressed``: SuperSplat/PlayCanvas's compressed PLY (chunks of 256 with min/max bounds, packed integers).
- ``spz``: Niantic's gzipped format (github.com/nianticlabs/spz), read by most current web viewers.

The first three are gsplat's ``export_splats`` (the library the GPU rasterizer already is); SPZ is written here from
Niantic's published layout (``spz_bytes``). Rows with a non-finite value are dropped first and counted.
"""

from __future__ import annotations

import gzip
import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from kc_splatfacto.atomic import atomic_write_bytes
from kc_splatfacto.errors import UserError

#: The parameter names of ``model.gauss_params`` that an export carries.
PARAM_NAMES = ("means", "scales", "quats", "opacities", "features_dc", "features_rest")

#: Format names, as ``kc-export --format`` takes them.
FORMATS = ("ply", "splat", "ply-compressed", "spz")

#: File name endings that decide the format; the longest match wins (``.compressed.ply`` before ``.ply``).
EXTENSIONS = {".compressed.ply": "ply-compressed", ".ply": "ply", ".splat": "splat", ".spz": "spz"}

#: gsplat's compressed PLY leaves out Gaussians at or below this opacity (its ``opacity_threshold``); we drop them
#: before the call so the count is ours to report.
COMPRESSED_PLY_MIN_OPACITY = 1 / 255

# SPZ constants from Niantic's reference (src/cc/load-spz.cc): the magic "NGSP", the version whose rotations are
# the smallest three components, the fixed-point precision of positions, the DC colour scale, and the bits kept
# for the degree-1 and the higher SH coefficients (its PackOptions defaults).
SPZ_MAGIC = 0x5053474E
SPZ_VERSION = 3
SPZ_FRACTIONAL_BITS = 12
SPZ_COLOR_SCALE = 0.15
SPZ_SH1_BITS = 5
SPZ_SH_REST_BITS = 4
SPZ_MAX_POINTS = 10_000_000  # the reference reader refuses more
SPZ_FLAG_ANTIALIASED = 0x1
_SPZ_DEGREE_OF_REST = {0: 0, 3: 1, 8: 2, 15: 3, 24: 4}  # rest coefficients per channel -> SH degree


@dataclass
class ExportResult:
    """What :func:`export_gaussians` wrote.

    ``num_dropped``: rows with a non-finite value; ``num_transparent``: rows the format leaves out as invisible
    (``ply-compressed`` only: opacity at or below 1/255); ``sh_rest_coeffs``: rest coefficients per channel in the
    parameters (the ``splat`` format stores none of them).
    """

    path: Path
    format: str
    num_written: int
    num_dropped: int
    sh_rest_coeffs: int
    num_transparent: int = 0
    num_bytes: int = 0


def format_from_path(path: str | Path) -> str | None:
    """The format a file name implies (``scene.compressed.ply`` -> ``ply-compressed``), or None."""
    name = Path(path).name.lower()
    for ending in sorted(EXTENSIONS, key=len, reverse=True):
        if name.endswith(ending):
            return EXTENSIONS[ending]
    return None


def _as_numpy(value: torch.Tensor | np.ndarray, name: str) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().to("cpu", torch.float32).numpy()
    array = np.asarray(value, dtype=np.float32)
    if array.ndim == 0:
        raise ValueError(f"export: parameter '{name}' is a scalar, expected one row per Gaussian")
    return array


def checked_parameters(params: Mapping[str, torch.Tensor | np.ndarray]) -> dict[str, np.ndarray]:
    """The parameters as float32 numpy arrays of checked shapes.

    Args:
        params: ``means [N,3]``, ``scales [N,3]`` (log), ``quats [N,4]`` (wxyz), ``opacities [N,1]`` or ``[N]``
            (logit), ``features_dc [N,3]``, ``features_rest [N,K,3]`` (optional: K = 0 when absent).
    Returns:
        the same names, ``opacities`` as ``[N]`` and ``features_rest`` as ``[N,K,3]``.
    """
    missing = [name for name in PARAM_NAMES if name != "features_rest" and name not in params]
    if missing:
        raise KeyError(f"export: parameters {missing} missing; expected the keys of model.gauss_params {PARAM_NAMES}")
    means = _as_numpy(params["means"], "means")
    n = means.shape[0]
    expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "features_dc": (n, 3)}
    arrays = {}
    for name, shape in expected.items():
        arrays[name] = _as_numpy(params[name], name)
        if arrays[name].shape != shape:
            raise ValueError(f"export: '{name}' has shape {arrays[name].shape}, expected {shape}")
    opacities = _as_numpy(params["opacities"], "opacities").reshape(n, -1)
    if opacities.shape != (n, 1):
        raise ValueError(f"export: 'opacities' must be [N,1] or [N] with N={n}, got {opacities.shape}")
    arrays["opacities"] = opacities[:, 0]
    if "features_rest" in params and params["features_rest"] is not None:
        rest = _as_numpy(params["features_rest"], "features_rest")
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3:
            raise ValueError(f"export: 'features_rest' must be [N,K,3] with N={n}, got {rest.shape}")
    else:
        rest = np.zeros((n, 0, 3), np.float32)
    arrays["features_rest"] = rest
    return arrays


def _finite_tensors(params: Mapping[str, torch.Tensor | np.ndarray]) -> tuple[dict[str, torch.Tensor], int, int]:
    """The checked parameters as float32 CPU tensors without the rows that hold a NaN or Inf; (tensors, dropped, K).

    Dropped here, not by gsplat: its own filter reduces a NaN opacity over every row (``.any(dim=0)`` on an [N]
    tensor) and would drop all Gaussians for one bad opacity.
    """
    arrays = checked_parameters(params)
    n = arrays["means"].shape[0]
    finite = np.ones(n, bool)
    for value in arrays.values():
        finite &= np.isfinite(value.reshape(n, -1)).all(axis=1)
    tensors = {name: torch.from_numpy(np.ascontiguousarray(value[finite])) for name, value in arrays.items()}
    return tensors, int((~finite).sum()), arrays["features_rest"].shape[1]


def _gsplat_bytes(t: Mapping[str, torch.Tensor], fmt: str) -> bytes:
    try:  # imported here: gsplat takes seconds to import and only exports need it
        from gsplat import export_splats
    except ImportError as exc:  # gsplat before 1.5 (nerfstudio 1.1 pins 1.4.0) has no exporter
        raise UserError(
            f"the {fmt} writer is gsplat's export_splats (gsplat 1.5 or newer), which this environment lacks ({exc}): "
            "pip install 'gsplat>=1.5,<1.6', or export spz (written without gsplat); in nerfstudio's environment "
            "ns-export gaussian-splat writes a PLY"
        ) from exc

    data = export_splats(
        means=t["means"], scales=t["scales"], quats=t["quats"], opacities=t["opacities"],
        sh0=t["features_dc"][:, None, :], shN=t["features_rest"], format=fmt.replace("-", "_"),
    )
    if fmt == "ply-compressed" and t["features_rest"].shape[1] == 0:
        # gsplat declares an ``sh`` element even with no property; SuperSplat takes a compressed PLY of two
        # elements, or three with 9, 24 or 45 SH bytes, and refuses this one. The element has no bytes: drop its line.
        empty = f"element sh {t['means'].shape[0]}\n".encode()
        cut = data.index(b"end_header\n")
        data = data[:cut].replace(empty, b"") + data[cut:]
    return data


def _round_half_away(x: np.ndarray) -> np.ndarray:
    """C++'s std::round (halves away from zero), which the reference encoder uses; numpy's rounds halves to even."""
    return np.sign(x) * np.floor(np.abs(x) + 0.5)


def _to_uint8(x: np.ndarray) -> np.ndarray:
    return np.clip(_round_half_away(x), 0, 255).astype(np.uint8)


def spz_fractional_bits(means: np.ndarray) -> int:
    """12 (the reference's quarter-millimetre grid at metre scale), fewer when a coordinate would overflow the 24-bit
    signed fixed point; the header carries the value, and readers scale by it."""
    largest = float(np.abs(means).max()) if means.size else 0.0
    bits = SPZ_FRACTIONAL_BITS
    while bits > 0 and round(largest * (1 << bits)) > (1 << 23) - 1:
        bits -= 1
    if round(largest * (1 << bits)) > (1 << 23) - 1:
        raise ValueError(f"a coordinate of {largest:g} does not fit SPZ's 24-bit fixed point (at most {(1 << 23) - 1})")
    return bits


def _spz_rotations(quats_wxyz: np.ndarray) -> np.ndarray:
    """Version 3's smallest-three quaternions, [N, 4] bytes: the reference's packQuaternionSmallestThree, vectorized.

    SPZ orders quaternions x, y, z, w (the PLY's rot_1, rot_2, rot_3, rot_0). The largest component's index takes
    the top 2 bits; each other component, in index order, 10 bits: a sign bit (relative to the largest, made
    positive) and a 9-bit magnitude over [0, 1/sqrt(2)].
    """
    q = quats_wxyz[:, [1, 2, 3, 0]].astype(np.float64)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    largest = np.argmax(np.abs(q), axis=1)  # the first of equal magnitudes, as the reference's strict '>' picks
    negate = q[np.arange(q.shape[0]), largest] < 0
    comp = largest.astype(np.uint32)
    for i in range(4):
        others = largest != i
        negbit = ((q[:, i] < 0) ^ negate).astype(np.uint32)
        # never past 511: float rounding at exactly 1/sqrt(2) would otherwise carry into the sign bit
        mag = np.minimum(np.floor(511.0 * np.abs(q[:, i]) / math.sqrt(0.5) + 0.5), 511).astype(np.uint32)
        comp = np.where(others, (comp << np.uint32(10)) | (negbit << np.uint32(9)) | mag, comp)
    return comp.astype("<u4").view(np.uint8).reshape(-1, 4)


def _spz_quantize_sh(sh: np.ndarray, bits: int) -> np.ndarray:
    """The reference's SH bytes for coefficients in [-1, 1]: 128 + 128 x, rounded, then to a multiple of
    2^(8 - bits) (fewer distinct values gzip better); readers decode (byte - 128) / 128."""
    bucket = 1 << (8 - bits)
    q = _round_half_away(sh * 128.0) + 128.0
    q = np.floor((q + bucket // 2) / bucket) * bucket
    return np.clip(q, 0, 255).astype(np.uint8)


def spz_bytes(t: Mapping[str, torch.Tensor], antialiased: bool = False) -> bytes:
    """The Gaussians as an SPZ file (version 3), following Niantic's reference encoder (``packGaussians``).

    The gzip stream holds a 16-byte header (magic, version, count, SH degree, fractional bits, flags, reserved)
    and then, attribute by attribute: positions (24-bit signed fixed point, little endian), alphas
    (sigmoid x 255), colours (DC x 0.15 x 255 + 127.5), scales ((log scale + 10) x 16), rotations (smallest three),
    SH rest (coefficient-major, channel inner; degree 1 to 5 bits, higher to 4). Coordinates are stored as they
    are, with no axis flip: what Niantic's own ply_to_spz does, so the SPZ and the PLY show the same scene.
    """
    means = t["means"].numpy().astype(np.float64)
    n = means.shape[0]
    rest = t["features_rest"].numpy().astype(np.float64)
    k = rest.shape[1]
    if k not in _SPZ_DEGREE_OF_REST:
        raise ValueError(f"{k} SH rest coefficients per channel is no SH degree SPZ stores (0, 3, 8, 15 or 24)")
    if n > SPZ_MAX_POINTS:
        raise ValueError(f"{n} Gaussians: SPZ readers load at most {SPZ_MAX_POINTS}; export as ply instead")
    bits = spz_fractional_bits(means)
    fixed = _round_half_away(means * (1 << bits)).astype("<i4")
    positions = fixed.reshape(-1, 1).view(np.uint8)[:, :3]  # the low 3 bytes of each little-endian int32
    alphas = _to_uint8(1.0 / (1.0 + np.exp(-t["opacities"].numpy().astype(np.float64))) * 255.0)
    colors = _to_uint8(t["features_dc"].numpy().astype(np.float64) * (SPZ_COLOR_SCALE * 255.0) + 0.5 * 255.0)
    scales = _to_uint8((t["scales"].numpy().astype(np.float64) + 10.0) * 16.0)
    rotations = _spz_rotations(t["quats"].numpy())
    sh = np.concatenate([_spz_quantize_sh(rest[:, :3], SPZ_SH1_BITS), _spz_quantize_sh(rest[:, 3:], SPZ_SH_REST_BITS)],
                        axis=1) if k else np.zeros((n, 0, 3), np.uint8)
    flags = SPZ_FLAG_ANTIALIASED if antialiased else 0
    header = struct.pack("<IIIBBBB", SPZ_MAGIC, SPZ_VERSION, n, _SPZ_DEGREE_OF_REST[k], bits, flags, 0)
    body = b"".join(a.tobytes() for a in (positions, alphas, colors, scales, rotations, sh))
    # zlib's default level, as the reference (level 9 takes several times longer for a few percent); mtime=0: the same
    # Gaussians give the same bytes
    return gzip.compress(header + body, compresslevel=6, mtime=0)


def export_gaussians(path: str | Path, params: Mapping[str, torch.Tensor | np.ndarray], fmt: str = "ply",
                     antialiased: bool = False) -> ExportResult:
    """Write the Gaussians (Splatfacto's ``gauss_params``: log scales, wxyz quaternions, logit opacities, SH DC and
    rest) to ``path`` in format ``fmt``, atomically (temp file + rename).

    Raises ValueError when nothing is left to write (every row non-finite or, for ``ply-compressed``, invisible)
    or the Gaussians do not fit the format. ``antialiased`` sets SPZ's flag (the run rasterized antialiased).
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; one of {', '.join(FORMATS)}")
    path = Path(path)
    t, num_dropped, k = _finite_tensors(params)
    num_transparent = 0
    if fmt == "ply-compressed":
        # the same float32 comparison gsplat makes, so its own filter then removes nothing
        visible = torch.sigmoid(t["opacities"]) > COMPRESSED_PLY_MIN_OPACITY
        num_transparent = int((~visible).sum())
        t = {name: value[visible] for name, value in t.items()}
    n = t["means"].shape[0]
    if n == 0:
        what = "visible" if num_transparent else "finite"
        left_out = f"{num_dropped} non-finite" + (f", {num_transparent} transparent" if num_transparent else "")
        raise ValueError(f"no {what} Gaussian left to write to {path} ({left_out} dropped)")
    data = spz_bytes(t, antialiased) if fmt == "spz" else _gsplat_bytes(t, fmt)
    atomic_write_bytes(path, data)
    return ExportResult(path=path, format=fmt, num_written=n, num_dropped=num_dropped, sh_rest_coeffs=k,
                        num_transparent=num_transparent, num_bytes=len(data))
