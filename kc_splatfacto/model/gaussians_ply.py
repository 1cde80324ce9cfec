"""Inria-style 3D Gaussian Splatting PLY files: export the Gaussians and import them back.

Layout (what the original 3DGS code, gsplat's exporter and viewers such as SuperSplat read and write), one
``vertex`` element, binary little endian, every property ``float``::

    x y z  f_dc_0 f_dc_1 f_dc_2  f_rest_0 .. f_rest_{3K-1}  opacity  scale_0 scale_1 scale_2  rot_0 .. rot_3

- ``f_rest_*`` are in Inria's channel-major order: the ``[N, K, 3]`` rest coefficients are transposed to
  ``[N, 3, K]`` before flattening, so ``f_rest_0..K-1`` are the red channel's K coefficients, then green, then blue.
- ``opacity`` is the raw logit, ``scale_*`` the log scales, ``rot_*`` the unnormalized quaternion (w, x, y, z):
  exactly the optimized parameters, no activation applied. Files from Inria's code also carry zero normals
  (``nx ny nz``); the reader takes properties by name, so both import.

The writer is gsplat's (:mod:`kc_splatfacto.model.export`); rows with any non-finite value are dropped on export (a
viewer would otherwise fail on the whole file) and counted.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
import torch

from kc_splatfacto.data.ply import read_ply_vertices
from kc_splatfacto.model.export import ExportResult, export_gaussians

#: What :func:`export_ply` returns (the path, rows written and rows dropped for non-finite values).
PlyExportResult = ExportResult


def ply_property_names(sh_rest_coeffs: int) -> list[str]:
    """The vertex property names, in file order, for ``sh_rest_coeffs`` (K) rest coefficients per channel."""
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * sh_rest_coeffs)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return names


def export_ply(path: str | Path, params: Mapping[str, torch.Tensor | np.ndarray]) -> ExportResult:
    """Write the Gaussians as an Inria-style binary little-endian PLY, atomically (temp file + rename).

    Rows holding any NaN or Inf are dropped; :attr:`ExportResult.num_dropped` says how many.
    Raises ValueError when no finite row is left (an empty splat file is never what the user wants).
    """
    return export_gaussians(path, params, "ply")


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
