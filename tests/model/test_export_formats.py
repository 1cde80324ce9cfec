"""Each export format read back by a reader written here from the format's published description (not from the
writer), equal to the exported Gaussians within the format's quantisation; compressed files at least 3x smaller.

The readers: a plain binary-PLY table parser (every format but splat and spz is a PLY), SuperSplat/PlayCanvas's
compressed-PLY decoding (splat-transform's ``decompressPly``: lerp within the chunk's min/max, 11-10-11 and 8-8-8-8
unorms, 2-10-10-10 smallest-three quaternions, SH bytes ``((q + 0.5) / 256 - 0.5) * 8``), antimatter15's 32-byte
records, and Niantic's SPZ (README "File Format" and ``unpackGaussians`` in src/cc/load-spz.cc).
"""

from __future__ import annotations

import gzip
import math
import struct

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from kc_splatfacto.data.ply import read_ply_vertices
from kc_splatfacto.model.export import COMPRESSED_PLY_MIN_OPACITY, export_gaussians, format_from_path
from kc_splatfacto.model.gaussians_ply import import_ply

SH_C0 = 0.28209479177387814
N = 3000  # a few thousand Gaussians, SH degree 3 (15 rest coefficients per channel)


def synthetic_gaussians(n: int = N, k: int = 15, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random Gaussians inside every format's range: distinct positions, SH rest in [-0.9, 0.9] (SPZ keeps [-1, 1)),
    DC colours within SPZ's +-3.3; a few nearly transparent ones for the compressed PLY's cut."""
    rng = np.random.default_rng(seed)
    params = {
        "means": rng.uniform(-5, 5, size=(n, 3)),
        "scales": rng.uniform(-6, 0, size=(n, 3)),
        "quats": rng.normal(size=(n, 4)),
        "opacities": rng.normal(scale=2.0, size=(n, 1)),
        "features_dc": rng.normal(scale=0.8, size=(n, 3)).clip(-3, 3),
        "features_rest": rng.uniform(-0.9, 0.9, size=(n, k, 3)),
    }
    params["opacities"][:7] = -8.0  # sigmoid < 1/255
    return {name: torch.tensor(value, dtype=torch.float32) for name, value in params.items()}


def as_numpy(params) -> dict[str, np.ndarray]:
    out = {name: value.numpy().astype(np.float64) for name, value in params.items()}
    out["opacities"] = out["opacities"].reshape(-1)
    out["quats"] = out["quats"] / np.linalg.norm(out["quats"], axis=1, keepdims=True)
    return out


def sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def quat_error(decoded: np.ndarray, original: np.ndarray) -> np.ndarray:
    """Per-component error between unit quaternions up to sign (q and -q are the same rotation)."""
    return np.minimum(np.abs(decoded - original), np.abs(decoded + original))


# ---------------------------------------------------------------------------------------------- independent readers


PLY_TYPES = {"float": "<f4", "uint": "<u4", "uchar": "u1", "int": "<i4", "double": "<f8", "ushort": "<u2"}


def read_binary_ply(data: bytes) -> tuple[list[str], dict[str, np.ndarray]]:
    """A binary little-endian PLY with scalar properties: (header lines, element name -> structured array)."""
    cut = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:cut].decode("ascii").splitlines()
    assert header[:2] == ["ply", "format binary_little_endian 1.0"], header[:2]
    elements: list[tuple[str, int, list]] = []
    for line in header:
        parts = line.split()
        if parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            elements[-1][2].append((parts[2], PLY_TYPES[parts[1]]))
    tables, offset = {}, cut
    for name, count, props in elements:
        dtype = np.dtype(props)
        tables[name] = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
        offset += dtype.itemsize * count
    assert offset == len(data), "bytes left after the last element"
    return header, tables


def unorm(value: np.ndarray, shift: int, bits: int) -> np.ndarray:
    return ((value >> np.uint32(shift)) & np.uint32((1 << bits) - 1)).astype(np.float64) / ((1 << bits) - 1)


def read_compressed_ply(data: bytes) -> dict[str, np.ndarray]:
    """SuperSplat's compressed PLY, decoded as splat-transform's decompressPly does."""
    _, tables = read_binary_ply(data)
    chunk, vertex = tables["chunk"], tables["vertex"]
    n = len(vertex)
    assert len(chunk) == math.ceil(n / 256)
    ci = np.arange(n) // 256

    def lerp(lo: str, hi: str, t):
        a, b = chunk[lo][ci].astype(np.float64), chunk[hi][ci].astype(np.float64)
        return a * (1 - t) + b * t, b - a

    pos, scl, col = vertex["packed_position"], vertex["packed_scale"], vertex["packed_color"]
    out: dict[str, np.ndarray] = {}
    fields = (("x", 21, 11), ("y", 11, 10), ("z", 0, 11))
    means, scales, steps_m, steps_s = [], [], [], []
    for (axis, shift, bits), s_axis in zip(fields, "xyz"):
        value, span = lerp(f"min_{axis}", f"max_{axis}", unorm(pos, shift, bits))
        means.append(value)
        steps_m.append(span / ((1 << bits) - 1))
        value, span = lerp(f"min_scale_{s_axis}", f"max_scale_{s_axis}", unorm(scl, shift, bits))
        scales.append(value)
        steps_s.append(span / ((1 << bits) - 1))
    out["means"], out["means_step"] = np.stack(means, 1), np.stack(steps_m, 1)
    out["scales"], out["scales_step"] = np.stack(scales, 1), np.stack(steps_s, 1)
    colours, steps_c = [], []
    for c, shift in zip("rgb", (24, 16, 8)):
        value, span = lerp(f"min_{c}", f"max_{c}", unorm(col, shift, 8))
        colours.append(value)
        steps_c.append(span / 255)
    out["colour"], out["colour_step"] = np.stack(colours, 1), np.stack(steps_c, 1)
    out["alpha"] = unorm(col, 0, 8)
    rot = vertex["packed_rotation"]
    norm = 1.0 / (math.sqrt(2) * 0.5)
    small = np.stack([(unorm(rot, s, 10) - 0.5) * norm for s in (20, 10, 0)], 1)
    largest = (rot >> np.uint32(30)).astype(int)
    m = np.sqrt(np.maximum(0.0, 1.0 - (small ** 2).sum(1)))
    quats = np.empty((n, 4))
    for i in range(n):  # the largest component's slot, the other three in index order
        others = [j for j in range(4) if j != largest[i]]
        quats[i, largest[i]] = m[i]
        quats[i, others] = small[i]
    out["quats"], out["largest"] = quats, largest
    if "sh" in tables and tables["sh"].dtype.names:
        sh = tables["sh"]
        q = np.stack([sh[f"f_rest_{j}"] for j in range(len(sh.dtype.names))], 1).astype(np.float64)
        t = np.where(q == 0, 0.0, np.where(q == 255, 1.0, (q + 0.5) / 256))
        k = q.shape[1] // 3
        out["features_rest"] = ((t - 0.5) * 8).reshape(n, 3, k).transpose(0, 2, 1)  # channel-major f_rest
    return out


def read_splat(data: bytes) -> dict[str, np.ndarray]:
    """antimatter15's .splat: 32-byte records of float32 x y z, float32 linear scales, uint8 RGBA, uint8 quaternion
    (w x y z) as 128 + 128 q."""
    assert len(data) % 32 == 0
    rec = np.frombuffer(data, dtype=np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4),
                                              ("rot", "u1", 4)]))
    return {"means": rec["pos"].astype(np.float64), "scales": rec["scale"].astype(np.float64),
            "rgba": rec["rgba"].astype(np.float64) / 255, "quats": (rec["rot"].astype(np.float64) - 128) / 128}


def read_spz(data: bytes) -> dict[str, np.ndarray]:
    """Niantic's SPZ: gzip of a 16-byte header, then positions, alphas, colours, scales, rotations, SH."""
    raw = gzip.decompress(data)
    magic, version, n, degree, fractional_bits, flags, reserved = struct.unpack_from("<IIIBBBB", raw, 0)
    assert (magic, version, reserved) == (0x5053474E, 3, 0), (hex(magic), version, reserved)
    assert not flags & 0x2, "no extensions expected"
    k = {0: 0, 1: 3, 2: 8, 3: 15, 4: 24}[degree]
    offset = 16

    def take(count: int) -> np.ndarray:
        nonlocal offset
        chunk = np.frombuffer(raw, dtype=np.uint8, count=count, offset=offset)
        offset += count
        return chunk

    p = take(n * 9).reshape(n * 3, 3).astype(np.int32)
    fixed = p[:, 0] | (p[:, 1] << 8) | (p[:, 2] << 16)
    fixed = np.where(fixed & 0x800000, fixed - (1 << 24), fixed)  # sign extension of the 24-bit value
    out = {"means": (fixed.astype(np.float64) / (1 << fractional_bits)).reshape(n, 3), "flags": flags}
    out["alpha"] = take(n).astype(np.float64) / 255
    out["features_dc"] = (take(n * 3).astype(np.float64).reshape(n, 3) / 255 - 0.5) / 0.15
    out["scales"] = take(n * 3).astype(np.float64).reshape(n, 3) / 16 - 10
    comp = take(n * 4).reshape(n, 4).astype(np.uint32)
    comp = comp[:, 0] | (comp[:, 1] << 8) | (comp[:, 2] << 16) | (comp[:, 3] << 24)
    largest = (comp >> 30).astype(int)
    xyzw = np.zeros((n, 4))
    rest = comp.copy()
    for slot in range(3, -1, -1):  # the last stored component sits in the lowest 10 bits
        here = largest != slot
        mag = (rest & 511).astype(np.float64) * math.sqrt(0.5) / 511
        sign = np.where((rest >> 9) & 1, -1.0, 1.0)
        xyzw[here, slot] = (sign * mag)[here]
        rest = np.where(here, rest >> 10, rest)
    xyzw[np.arange(n), largest] = np.sqrt(np.maximum(0.0, 1 - (xyzw ** 2).sum(1)))
    out["quats"], out["largest"] = xyzw[:, [3, 0, 1, 2]], np.array([1, 2, 3, 0])[largest]  # as w x y z
    out["features_rest"] = (take(n * k * 3).astype(np.float64).reshape(n, k, 3) - 128) / 128
    assert offset == len(raw), "bytes left after the SH"
    return out


# ---------------------------------------------------------------------------------------------------------- tests


@pytest.fixture(scope="module")
def gaussians():
    return synthetic_gaussians()


@pytest.fixture(scope="module")
def written(gaussians, tmp_path_factory):
    folder = tmp_path_factory.mktemp("formats")
    return {fmt: export_gaussians(folder / f"g.{fmt}", gaussians, fmt) for fmt in
            ("ply", "splat", "ply-compressed", "spz")}


def test_format_from_the_file_name():
    assert [format_from_path(p) for p in ("a.ply", "b.SPLAT", "c.compressed.ply", "d.spz", "e.bin", "f")] == [
        "ply", "splat", "ply-compressed", "spz", None, None]


def test_ply_is_exact(gaussians, written):
    """float32 throughout: read back bit for bit by the project's own PLY reader (independent of gsplat's writer)."""
    result = written["ply"]
    assert (result.num_written, result.num_dropped) == (N, 0)
    back = import_ply(result.path)
    for name, value in gaussians.items():
        assert torch.equal(back[name], value), name


def test_compressed_ply_within_its_quantisation(gaussians, written):
    g = as_numpy(gaussians)
    visible = sigmoid(g["opacities"]) > COMPRESSED_PLY_MIN_OPACITY
    result = written["ply-compressed"]
    assert (result.num_written, result.num_transparent) == (int(visible.sum()), N - int(visible.sum()))
    assert result.num_transparent >= 7  # the ones set to a logit of -8 at least
    d = read_compressed_ply(result.path.read_bytes())
    g = {name: value[visible] for name, value in g.items()}
    # gsplat orders the Gaussians along a Morton curve: each decoded one is matched to the nearest original, and the
    # matching must be one to one
    dist, match = cKDTree(g["means"]).query(d["means"])
    assert np.array_equal(np.sort(match), np.arange(len(match)))
    g = {name: value[match] for name, value in g.items()}
    eps = 1e-5  # float32 bounds and lerp
    # positions: 11, 10, 11 bits over the chunk's range, rounded to nearest -> half a step
    assert (np.abs(d["means"] - g["means"]) <= d["means_step"] / 2 + eps).all()
    # log scales: the same packing over the chunk's scale range
    assert (np.abs(d["scales"] - g["scales"]) <= d["scales_step"] / 2 + eps).all()
    # base colour (0.5 + C0 dc): 8 bits over the chunk's colour range; opacity: 8 bits of the sigmoid
    colour = 0.5 + SH_C0 * g["features_dc"]
    assert (np.abs(d["colour"] - colour) <= d["colour_step"] / 2 + eps).all()
    assert (np.abs(d["alpha"] - sigmoid(g["opacities"])) <= 0.5 / 255 + eps).all()
    # quaternions: three components in 10 bits over [-1/sqrt2, 1/sqrt2] (half a step: sqrt2/2046), the largest
    # recomputed from them (within 3 of those steps, since it is at least 1/2)
    step = math.sqrt(2) / 2046
    err = quat_error(d["quats"], g["quats"])
    largest = np.eye(4, dtype=bool)[d["largest"]]
    assert (err[~largest] <= step + eps).all() and (err[largest] <= 3 * step + eps).all()
    # SH rest: truncated to 1/32 steps over [-4, 4), decoded at the step's middle -> within 1/64
    assert (np.abs(d["features_rest"] - g["features_rest"]) <= 1 / 64 + eps).all()


def test_splat_within_its_quantisation(gaussians, written):
    g = as_numpy(gaussians)
    d = read_splat(written["splat"].path.read_bytes())
    assert len(d["means"]) == N
    # positions are float32: exact, so they identify each record (gsplat reorders them)
    order = {tuple(row): i for i, row in enumerate(gaussians["means"].numpy().tolist())}
    match = np.array([order[tuple(row)] for row in d["means"].astype(np.float32).tolist()])
    assert np.array_equal(np.sort(match), np.arange(N))
    g = {name: value[match] for name, value in g.items()}
    np.testing.assert_allclose(d["scales"], np.exp(g["scales"]), rtol=1e-6)  # linear scales, float32
    # colour and opacity as bytes, truncated: the byte / 255 is below the value by less than 1/255 (colour clipped
    # to [0, 1]: no SH rest, no headroom)
    rgba = np.concatenate([np.clip(0.5 + SH_C0 * g["features_dc"], 0, 1), sigmoid(g["opacities"])[:, None]], 1)
    diff = rgba - d["rgba"]
    assert (diff >= -1e-6).all() and (diff < 1 / 255 + 1e-6).all()
    # quaternion (w x y z) as 128 + 128 q, truncated: within 1/128
    assert (np.abs(d["quats"] - g["quats"]) <= 1 / 128 + 1e-6).all()


def test_spz_within_its_quantisation(gaussians, written):
    g = as_numpy(gaussians)
    d = read_spz(written["spz"].path.read_bytes())
    assert len(d["means"]) == N and d["flags"] == 0  # the same order as the input
    # positions: 24-bit fixed point with 12 fractional bits (|x| < 2048), rounded -> half of 1/4096
    assert (np.abs(d["means"] - g["means"]) <= 0.5 / 4096 + 1e-7).all()
    assert (np.abs(d["alpha"] - sigmoid(g["opacities"])) <= 0.5 / 255 + 1e-6).all()  # sigmoid in 8 bits, rounded
    # DC colour as 127.5 + 0.15 * 255 dc in 8 bits, rounded: half of 1/(0.15 * 255) (for |dc| <= 3.33)
    assert (np.abs(d["features_dc"] - g["features_dc"]) <= 0.5 / (0.15 * 255) + 1e-6).all()
    # log scales as (s + 10) * 16 in 8 bits, rounded: within 1/32 (for s in [-10, 5.9])
    assert (np.abs(d["scales"] - g["scales"]) <= 1 / 32 + 1e-6).all()
    # quaternions: smallest three as sign + 9 bits over [0, 1/sqrt2] (half a step: sqrt(1/2) / 1022), the largest
    # recomputed (within 3 of those steps)
    step = math.sqrt(0.5) / 1022
    err = quat_error(d["quats"], g["quats"])
    largest = np.eye(4, dtype=bool)[d["largest"]]
    assert (err[~largest] <= step + 1e-6).all() and (err[largest] <= 3 * step + 1e-6).all()
    # SH rest: 128 + 128 x rounded, then to multiples of 8 (degree 1: 5 bits) or 16 (higher: 4 bits) -> within
    # 4.5/128 and 8.5/128 of the value (for x in [-1, 1))
    err = np.abs(d["features_rest"] - g["features_rest"])
    assert (err[:, :3] <= 4.5 / 128 + 1e-6).all() and (err[:, 3:] <= 8.5 / 128 + 1e-6).all()


def test_compressed_files_at_least_3x_smaller(written):
    ply = written["ply"].num_bytes
    assert ply == written["ply"].path.stat().st_size
    for fmt in ("ply-compressed", "spz"):
        assert written[fmt].path.stat().st_size * 3 <= ply, (fmt, written[fmt].path.stat().st_size, ply)


def test_non_finite_rows_dropped_in_every_format(tmp_path):
    params = synthetic_gaussians(n=300, seed=1)
    params["means"][3, 0] = float("nan")
    params["opacities"][5, 0] = float("nan")  # gsplat's own filter would drop every row for this one
    params["features_rest"][9, 14, 2] = float("inf")
    for fmt in ("ply", "splat", "ply-compressed", "spz"):
        result = export_gaussians(tmp_path / f"g.{fmt}", params, fmt)
        assert result.num_dropped == 3, fmt
        assert result.num_written + result.num_transparent == 297, fmt
    assert len(read_ply_vertices(tmp_path / "g.ply")) == 297
    assert len(read_splat((tmp_path / "g.splat").read_bytes())["means"]) == 297
    assert len(read_spz((tmp_path / "g.spz").read_bytes())["means"]) == 297


def test_spz_far_coordinates_use_fewer_fractional_bits(tmp_path):
    """24 bits with 12 fractional reach +-2048: a scene of larger coordinates keeps its positions (the header says
    how many fractional bits) rather than wrapping around."""
    params = synthetic_gaussians(n=50, seed=2)
    params["means"][0] = torch.tensor([5000.0, -3000.0, 100.0])
    result = export_gaussians(tmp_path / "far.spz", params, "spz")
    raw = gzip.decompress(result.path.read_bytes())
    assert raw[13] == 10  # 5000 * 2^10 < 2^23 <= 5000 * 2^11
    d = read_spz(result.path.read_bytes())
    assert (np.abs(d["means"] - params["means"].numpy()) <= 0.5 / 1024 + 1e-6).all()


def test_degree_zero_compressed_ply_has_no_sh_element(tmp_path):
    """SuperSplat accepts a compressed PLY of two elements, or three with 9, 24 or 45 SH bytes: an empty ``sh``
    element would make it refuse the file."""
    params = synthetic_gaussians(n=40, seed=3)
    del params["features_rest"]
    result = export_gaussians(tmp_path / "g.compressed.ply", params, "ply-compressed")
    header, tables = read_binary_ply(result.path.read_bytes())
    assert list(tables) == ["chunk", "vertex"], header
    spz = read_spz(export_gaussians(tmp_path / "g.spz", params, "spz").path.read_bytes())
    assert spz["features_rest"].shape == (40, 0, 3)


def test_nothing_to_write_is_an_error(tmp_path):
    params = synthetic_gaussians(n=5)
    params["opacities"][:] = -9.0
    with pytest.raises(ValueError, match="no visible Gaussian"):
        export_gaussians(tmp_path / "g.compressed.ply", params, "ply-compressed")
    params["scales"][:] = float("nan")
    for fmt in ("ply", "spz"):
        with pytest.raises(ValueError, match="no finite Gaussian"):
            export_gaussians(tmp_path / f"g.{fmt}", params, fmt)
    assert not list(tmp_path.iterdir())


def test_spz_antialiased_flag(tmp_path):
    """Header flag 0x1: the Gaussians were trained with antialiased rasterization (viewers then render them so)."""
    params = synthetic_gaussians(n=10)
    assert read_spz(export_gaussians(tmp_path / "a.spz", params, "spz", antialiased=True).path.read_bytes())["flags"] == 1
    assert read_spz(export_gaussians(tmp_path / "c.spz", params, "spz").path.read_bytes())["flags"] == 0


def test_without_gsplat_exporter_is_one_clear_error(tmp_path, monkeypatch):
    """nerfstudio 1.1 pins gsplat 1.4.0, which has no export_splats: the gsplat formats say so and what to do, SPZ
    (written here) still works."""
    import sys
    import types

    from kc_splatfacto.errors import UserError

    monkeypatch.setitem(sys.modules, "gsplat", types.ModuleType("gsplat"))  # a gsplat without export_splats
    params = synthetic_gaussians(n=10)
    with pytest.raises(UserError, match=r"gsplat 1\.5 or newer.*spz"):
        export_gaussians(tmp_path / "g.ply", params, "ply")
    assert not (tmp_path / "g.ply").exists()
    assert len(read_spz(export_gaussians(tmp_path / "g.spz", params, "spz").path.read_bytes())["means"]) == 10
