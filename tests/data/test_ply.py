"""kc_splatfacto/data/ply.py, the one PLY reader, against trimesh (an independent writer and reader) and against
files written here byte by byte with numpy (ascii, big endian)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kc_splatfacto.data.ply import read_ply_points, read_ply_vertices
from kc_splatfacto.model.gaussians_ply import export_ply, import_ply, ply_property_names

trimesh = pytest.importorskip("trimesh")


def _cloud(n=50, seed=0):
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * 10.0
    rgba = np.concatenate([rng.integers(0, 256, size=(n, 3)), np.full((n, 1), 255)], 1).astype(np.uint8)
    return xyz, rgba


@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_point_cloud_written_by_trimesh(tmp_path, encoding):
    xyz, rgba = _cloud()
    path = tmp_path / "points.ply"
    path.write_bytes(trimesh.PointCloud(xyz, colors=rgba).export(file_type="ply", encoding=encoding))
    got_xyz, got_rgb = read_ply_points(path)
    reference = trimesh.load(str(path), process=False)
    np.testing.assert_array_equal(got_xyz, np.asarray(reference.vertices, np.float64))
    np.testing.assert_allclose(got_xyz, xyz, rtol=1e-6 if encoding == "binary" else 1e-7)
    np.testing.assert_array_equal(got_rgb, rgba[:, :3])


def test_mesh_vertices_before_faces(tmp_path):
    """A mesh PLY (vertices, then a list-valued face element) gives its vertices; colourless means grey."""
    box = trimesh.creation.box()
    path = tmp_path / "box.ply"
    path.write_bytes(box.export(file_type="ply", encoding="binary"))
    xyz, rgb = read_ply_points(path)
    np.testing.assert_allclose(xyz, box.vertices, rtol=1e-6)
    assert rgb.shape == (len(box.vertices), 3)


def test_big_endian_and_ascii_3dgs_files_import_like_the_binary_one(tmp_path):
    rng = np.random.default_rng(3)
    n, k = 7, 3
    params = {
        "means": torch.tensor(rng.normal(size=(n, 3)), dtype=torch.float32),
        "scales": torch.tensor(rng.normal(size=(n, 3)), dtype=torch.float32),
        "quats": torch.tensor(rng.normal(size=(n, 4)), dtype=torch.float32),
        "opacities": torch.tensor(rng.normal(size=(n, 1)), dtype=torch.float32),
        "features_dc": torch.tensor(rng.normal(size=(n, 3)), dtype=torch.float32),
        "features_rest": torch.tensor(rng.normal(size=(n, k, 3)), dtype=torch.float32),
    }
    binary = import_ply(export_ply(tmp_path / "le.ply", params).path)
    rows = read_ply_vertices(tmp_path / "le.ply")
    names = ply_property_names(k)
    header = "ply\nformat {}\nelement vertex {}\n" + "".join(f"property float {p}\n" for p in names) + "end_header\n"
    table = np.stack([rows[p] for p in names], axis=1).astype(np.float32)
    (tmp_path / "be.ply").write_bytes(header.format("binary_big_endian 1.0", n).encode() + table.astype(">f4").tobytes())
    (tmp_path / "ascii.ply").write_text(
        header.format("ascii 1.0", n) + "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in table)
    )
    for other in ("be.ply", "ascii.ply"):
        imported = import_ply(tmp_path / other)
        for name, value in binary.items():
            assert torch.equal(imported[name], value), (other, name)
    for name, value in params.items():
        assert torch.equal(binary[name], value), name


def test_bad_files_name_the_file(tmp_path):
    xyz, rgba = _cloud(n=20)
    good = trimesh.PointCloud(xyz, colors=rgba).export(file_type="ply", encoding="binary")
    (tmp_path / "cut.ply").write_bytes(good[:-40])
    with pytest.raises(ValueError, match="cut.ply: truncated"):
        read_ply_points(tmp_path / "cut.ply")
    (tmp_path / "text.ply").write_text("ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
                                       "property float z\nend_header\n1 2 3\n4 five 6\n")
    with pytest.raises(ValueError, match="text.ply: a vertex line"):
        read_ply_points(tmp_path / "text.ply")
    (tmp_path / "short.ply").write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                                        "property float z\nend_header\n1 2 3\n")
    with pytest.raises(ValueError, match="short.ply: truncated"):
        read_ply_points(tmp_path / "short.ply")
    (tmp_path / "odd.ply").write_text("ply\nformat binary_middle_endian 1.0\nend_header\n")
    with pytest.raises(ValueError, match="odd.ply: PLY format"):
        read_ply_points(tmp_path / "odd.ply")
    (tmp_path / "not.ply").write_text("hello\n")
    with pytest.raises(ValueError, match="not.ply is not a PLY file"):
        read_ply_points(tmp_path / "not.ply")
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        read_ply_points(tmp_path / "missing.ply")
