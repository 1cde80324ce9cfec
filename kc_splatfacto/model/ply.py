"""Inria-style 3D Gaussian Splatting PLY files: export the Gaussians and import them back.

Layout (what the original 3DGS code, Splatfacto's exporter and viewers such as SuperSplat read and write), one
``vertex`` element, binary little endian, every property ``float``::

    x y z  nx ny nz  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3K-1}  opacity  scale_0 scale_1 scale_2  rot_0 .. rot_3

- ``f_rest_*`` are in Inria's channel-major order: the ``[N, K, 3]`` rest coefficients are transposed to
  ``[N, 3, K]`` before flattening, so ``f_rest_0..K-1`` are the red channel's K coefficients, then green, then blue.
- ``opacity`` is the raw logit, ``scale_*`` the log scales, ``rot_*`` the unnormalized quaternion (w, x, y, z):
  exactly the optimized parameters, no activation applied. Normals are zeros (the format carries them, 3DGS does not).

Rows with any non-finite value are dropped on export (a viewer would otherwise fail on the whole file); the count is
returned so the caller can report it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from kc_splatfacto.atomic import atomic_write_bytes
from kc_splatfacto.data.ply import read_ply_vertices

#: The parameter names of ``model.gauss_params`` that a PLY file carries.
PLY_PARAM_NAMES = ("means", "scales", "quats", "opacities", "features_dc", "features_rest")

@dataclass
class PlyExportResult:
    """What :func:`export_ply` wrote: the path, rows written and rows dropped for non-finite values."""

    path: Path
    num_written: int
    num_dropped: int
    sh_rest_coeffs: int


def _as_numpy(value: torch.Tensor | np.ndarray, name: str) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        value = value.detach().to("cpu", torch.float32).numpy()
    array = np.asarray(value, dtype=np.float32)
    if array.ndim == 0:
        raise ValueError(f"export_ply: parameter '{name}' is a scalar, expected one row per Gaussian")
    return array


def ply_property_names(sh_rest_coeffs: int) -> list[str]:
    """The vertex property names, in file order, for ``sh_rest_coeffs`` (K) rest coefficients per channel."""
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * sh_rest_coeffs)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def gaussians_to_rows(params: Mapping[str, torch.Tensor | np.ndarray]) -> tuple[np.ndarray, int]:
    """Pack Splatfacto parameters into the PLY's ``[N, P]`` float32 row matrix.

    Args:
        params: ``means [N,3]``, ``scales [N,3]`` (log), ``quats [N,4]`` (wxyz), ``opacities [N,1]`` or ``[N]``
            (logit), ``features_dc [N,3]``, ``features_rest [N,K,3]`` (optional: K = 0 when absent).
    Returns:
        (rows [N, 17 + 3K] in :func:`ply_property_names` order, K).
    """
    missing = [name for name in PLY_PARAM_NAMES if name != "features_rest" and name not in params]
    if missing:
        raise KeyError(f"export_ply: parameters {missing} missing; expected the keys of model.gauss_params {PLY_PARAM_NAMES}")
    means = _as_numpy(params["means"], "means")
    n = means.shape[0]
    expected = {"means": (n, 3), "scales": (n, 3), "quats": (n, 4), "features_dc": (n, 3)}
    arrays = {}
    for name, shape in expected.items():
        arrays[name] = _as_numpy(params[name], name)
        if arrays[name].shape != shape:
            raise ValueError(f"export_ply: '{name}' has shape {arrays[name].shape}, expected {shape}")
    opacities = _as_numpy(params["opacities"], "opacities").reshape(n, -1)
    if opacities.shape != (n, 1):
        raise ValueError(f"export_ply: 'opacities' must be [N,1] or [N] with N={n}, got {opacities.shape}")
    if "features_rest" in params and params["features_rest"] is not None:
        rest = _as_numpy(params["features_rest"], "features_rest")
        if rest.ndim != 3 or rest.shape[0] != n or rest.shape[2] != 3:
            raise ValueError(f"export_ply: 'features_rest' must be [N,K,3] with N={n}, got {rest.shape}")
    else:
        rest = np.zeros((n, 0, 3), np.float32)
    k = rest.shape[1]
    rest_channel_major = rest.transpose(0, 2, 1).reshape(n, 3 * k)
    rows = np.concatenate(
        [means, np.zeros((n, 3), np.float32), arrays["features_dc"], rest_channel_major, opacities,
         arrays["scales"], arrays["quats"]],
        axis=1,
    )
    return rows.astype(np.float32, copy=False), k


def export_ply(path: str | Path, params: Mapping[str, torch.Tensor | np.ndarray]) -> PlyExportResult:
    """Write the Gaussians as an Inria-style binary little-endian PLY, atomically (temp file + rename).

    Rows holding any NaN or Inf are dropped; :attr:`PlyExportResult.num_dropped` says how many.
    Raises ValueError when no finite row is left (an empty splat file is never what the user wants).
    """
    path = Path(path)
    rows, k = gaussians_to_rows(params)
    finite = np.isfinite(rows).all(axis=1)
    num_dropped = int((~finite).sum())
    rows = rows[finite]
    if rows.shape[0] == 0:
        raise ValueError(f"export_ply: no finite Gaussian left to write to {path} ({num_dropped} non-finite rows dropped)")
    names = ply_property_names(k)
    structured = np.empty(rows.shape[0], dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        structured[name] = rows[:, i]
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {rows.shape[0]}"]
    header += [f"property float {name}" for name in names]
    header += ["end_header"]
    payload = ("\n".join(header) + "\n").encode("ascii") + structured.tobytes()
    atomic_write_bytes(path, payload)
    return PlyExportResult(path=path, num_written=int(rows.shape[0]), num_dropped=num_dropped, sh_rest_coeffs=k)


def import_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """Read an Inria-style 3DGS PLY back into Splatfacto's parameter dict (float32 CPU tensors).

    Returns:
        ``means [N,3]``, ``scales [N,3]`` (log), ``quats [N,4]`` (wxyz), ``opacities [N,1]`` (logit),
        ``features_dc [N,3]``, ``features_rest [N,K,3]`` (K = number of ``f_rest_*`` properties / 3).
    """
    vertices = read_ply_vertices(path)
    fields = set(vertices.dtype.names or ())
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity"] + [f"scale_{i}" for i in range(3)]
    required += [f"rot_{i}" for i in range(4)]
    missing = [name for name in required if name not in fields]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, vertex properties {missing} are missing")
    rest_names = sorted((n for n in fields if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    if len(rest_names) % 3:
        raise ValueError(f"{path}: {len(rest_names)} f_rest_* properties, expected a multiple of 3 (one set per channel)")
    k = len(rest_names) // 3

    def stack(names: list[str]) -> np.ndarray:
        if not names:
            return np.zeros((vertices.shape[0], 0), np.float32)
        return np.stack([vertices[n].astype(np.float32) for n in names], axis=1)

    n = vertices.shape[0]
    rest = stack(rest_names).reshape(n, 3, k).transpose(0, 2, 1)
    out = {
        "means": stack(["x", "y", "z"]),
        "scales": stack([f"scale_{i}" for i in range(3)]),
        "quats": stack([f"rot_{i}" for i in range(4)]),
        "opacities": stack(["opacity"]),
        "features_dc": stack(["f_dc_0", "f_dc_1", "f_dc_2"]),
        "features_rest": np.ascontiguousarray(rest),
    }
    return {name: torch.from_numpy(np.ascontiguousarray(value)) for name, value in out.items()}
