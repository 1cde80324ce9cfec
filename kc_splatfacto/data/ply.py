"""The one PLY reader: a PLY file's ``vertex`` element as a numpy structured array.

Used for seed point clouds (``read_ply_points``: xyz and colours, e.g. a transforms.json ``ply_file_path``) and, by
:func:`kc_splatfacto.model.gaussians_ply.import_ply`, for Inria-style 3DGS files. Reads ``ascii``,
``binary_little_endian`` and ``binary_big_endian`` files with scalar properties in the vertex element; other elements
(faces, edges) may follow the vertices and are not read. Every malformed file is a ``ValueError`` naming it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: PLY scalar type names (classic and sized spellings) -> numpy type codes without byte order
PLY_SCALAR_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_BYTE_ORDER = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": "<"}
#: grey for a point cloud without colours
DEFAULT_POINT_RGB = 128


def _parse_header(path: Path, data: bytes) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]], int]:
    """(format, [(element, count, [(property, type code)])], byte offset of the body)."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path} is not a PLY file (no 'ply' magic / 'end_header')")
    body_start = data.find(b"\n", end)
    body_start = len(data) if body_start < 0 else body_start + 1
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    fmt = next((line.split()[1] for line in lines if line.startswith("format") and len(line.split()) > 1), None)
    if fmt not in _BYTE_ORDER:
        raise ValueError(f"{path}: PLY format '{fmt}' is unknown (ascii, binary_little_endian, binary_big_endian)")
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    for line in lines:
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise ValueError(f"{path}: malformed header line '{line}'")
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ValueError(f"{path}: property before any element in the header")
            if parts[1] == "list":
                elements[-1][2].append((parts[-1], "list"))
                continue
            if len(parts) != 3 or parts[1] not in PLY_SCALAR_TYPES:
                raise ValueError(f"{path}: unknown PLY property type in '{line}'")
            elements[-1][2].append((parts[2], PLY_SCALAR_TYPES[parts[1]]))
    return fmt, elements, body_start


def read_ply_vertices(path: str | Path) -> np.ndarray:
    """The ``vertex`` element of a PLY file as a structured array [N] (one field per property, the file's types)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"PLY file {path} does not exist")
    data = path.read_bytes()
    fmt, elements, offset = _parse_header(path, data)
    order = _BYTE_ORDER[fmt]
    for name, count, props in elements:
        if name != "vertex":
            if fmt != "ascii" and any(code == "list" for _, code in props):
                raise ValueError(f"{path}: a list-valued element '{name}' precedes the vertices; cannot skip it")
            if fmt == "ascii":
                offset = _skip_ascii_lines(data, offset, count)
            else:
                offset += count * np.dtype([(p, order + code) for p, code in props]).itemsize
            continue
        if any(code == "list" for _, code in props):
            raise ValueError(f"{path}: list property in the vertex element is not supported")
        dtype = np.dtype([(p, order + code) for p, code in props])
        if fmt == "ascii":
            return _read_ascii_rows(path, data, offset, count, dtype)
        needed = offset + count * dtype.itemsize
        if len(data) < needed:
            raise ValueError(f"{path}: truncated ({len(data)} bytes, the header announces {needed})")
        return np.frombuffer(data, dtype=dtype, count=count, offset=offset).astype(dtype.newbyteorder("="))
    raise ValueError(f"{path}: no 'vertex' element in the header")


def _skip_ascii_lines(data: bytes, offset: int, count: int) -> int:
    for _ in range(count):
        offset = data.index(b"\n", offset) + 1
    return offset


def _read_ascii_rows(path: Path, data: bytes, offset: int, count: int, dtype: np.dtype) -> np.ndarray:
    if count == 0 or not dtype.names:
        return np.zeros(count, dtype=dtype.newbyteorder("="))
    rows = data[offset:].decode("ascii", errors="replace").splitlines()
    rows = [row for row in rows if row.strip()][:count]
    if len(rows) < count:
        raise ValueError(f"{path}: truncated ({len(rows)} vertex lines, the header announces {count})")
    try:
        table = np.array([row.split()[: len(dtype.names)] for row in rows], dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}: a vertex line is not {len(dtype.names)} numbers ({exc})") from exc
    if table.shape != (count, len(dtype.names)):
        raise ValueError(f"{path}: vertex lines must hold {len(dtype.names)} numbers each")
    out = np.empty(count, dtype=dtype.newbyteorder("="))
    for i, name in enumerate(dtype.names):
        out[name] = table[:, i]
    return out


def read_ply_points(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A point cloud: ([M, 3] float64 xyz, [M, 3] uint8 rgb). Colours from ``red/green/blue`` (uchar, or floats in
    [0, 1]); grey when the file has none."""
    vertices = read_ply_vertices(path)
    names = set(vertices.dtype.names or ())
    if not {"x", "y", "z"} <= names:
        raise ValueError(f"{path}: the vertices have no x, y, z properties")
    xyz = np.stack([vertices[c].astype(np.float64) for c in ("x", "y", "z")], axis=1).reshape(-1, 3)
    if {"red", "green", "blue"} <= names:
        rgb = np.stack([vertices[c] for c in ("red", "green", "blue")], axis=1)
        if rgb.dtype.kind == "f":
            rgb = np.clip(np.round(rgb * 255.0), 0, 255)
        rgb = rgb.astype(np.uint8)
    else:
        rgb = np.full((len(xyz), 3), DEFAULT_POINT_RGB, np.uint8)
    return xyz, rgb
