"""Inria-style PLY export/import: layout read back by an independent parser, round trip, non-finite rows dropped."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from kc_splatfacto.model.gaussians_ply import export_ply, import_ply, ply_property_names


def _random_params(n: int = 50, k: int = 15, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 3,
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.randn(n, 1, generator=g),
        "features_dc": torch.randn(n, 3, generator=g),
        "features_rest": torch.randn(n, k, 3, generator=g) * 0.1,
    }


def _parse_header_and_body(path):
    """Independent reader: split the header by hand and view the body as float32 rows."""
    data = path.read_bytes()
    marker = b"end_header\n"
    cut = data.index(marker) + len(marker)
    header = data[:cut].decode("ascii").splitlines()
    props = [line.split()[2] for line in header if line.startswith("property")]
    types = {line.split()[1] for line in header if line.startswith("property")}
    count = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    body = np.frombuffer(data[cut:], dtype="<f4").reshape(count, len(props))
    return header, props, types, body


def test_layout_matches_inria(tmp_path):
    params = _random_params(n=20, k=15)
    result = export_ply(tmp_path / "g.ply", params)
    header, props, types, body = _parse_header_and_body(result.path)
    assert header[0] == "ply" and header[1] == "format binary_little_endian 1.0"
    assert types == {"float"}
    # gsplat's layout: Inria's without the zero normals (nx ny nz), which 3DGS readers take by name or ignore
    expected = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
    expected += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert props == expected == ply_property_names(15)
    col = {name: i for i, name in enumerate(props)}
    np.testing.assert_array_equal(body[:, [col["x"], col["y"], col["z"]]], params["means"].numpy())
    np.testing.assert_array_equal(body[:, col["opacity"]], params["opacities"][:, 0].numpy())  # raw logit
    np.testing.assert_array_equal(body[:, col["scale_0"]:col["scale_2"] + 1], params["scales"].numpy())  # log scale
    np.testing.assert_array_equal(body[:, col["rot_0"]:col["rot_3"] + 1], params["quats"].numpy())
    # Inria's channel-major rest order: f_rest_{c*K + j} is coefficient j of channel c.
    rest = params["features_rest"].numpy()
    for c in range(3):
        for j in (0, 7, 14):
            np.testing.assert_array_equal(body[:, col[f"f_rest_{c * 15 + j}"]], rest[:, j, c])


def test_round_trip_exact(tmp_path):
    params = _random_params(n=64, k=3, seed=1)
    result = export_ply(tmp_path / "sub" / "g.ply", params)
    assert (result.num_written, result.num_dropped, result.sh_rest_coeffs) == (64, 0, 3)
    back = import_ply(result.path)
    assert set(back) == set(params)
    for name, value in params.items():
        assert back[name].shape == value.shape, name
        torch.testing.assert_close(back[name], value, rtol=0, atol=0)
    assert not list(result.path.parent.glob("*.tmp")), "atomic write left a temp file behind"


def test_degree_zero_has_no_rest(tmp_path):
    params = _random_params(n=5)
    del params["features_rest"]
    result = export_ply(tmp_path / "g.ply", params)
    _, props, _, _ = _parse_header_and_body(result.path)
    assert not any(p.startswith("f_rest") for p in props)
    assert import_ply(result.path)["features_rest"].shape == (5, 0, 3)


def test_non_finite_rows_dropped(tmp_path):
    params = _random_params(n=10)
    params["means"][2, 1] = float("nan")
    params["features_rest"][5, 4, 2] = float("inf")
    params["opacities"][7, 0] = float("-inf")
    result = export_ply(tmp_path / "g.ply", params)
    assert (result.num_written, result.num_dropped) == (7, 3)
    back = import_ply(result.path)
    keep = [i for i in range(10) if i not in (2, 5, 7)]
    torch.testing.assert_close(back["means"], params["means"][keep], rtol=0, atol=0)
    torch.testing.assert_close(back["features_rest"], params["features_rest"][keep], rtol=0, atol=0)


def test_all_non_finite_is_an_error(tmp_path):
    params = _random_params(n=3)
    params["scales"][:] = float("nan")
    with pytest.raises(ValueError, match="no finite Gaussian"):
        export_ply(tmp_path / "g.ply", params)
    assert not (tmp_path / "g.ply").exists()


def test_bad_inputs_name_the_problem(tmp_path):
    params = _random_params(n=4)
    del params["quats"]
    with pytest.raises(KeyError, match="quats"):
        export_ply(tmp_path / "g.ply", params)
    params = _random_params(n=4)
    params["scales"] = params["scales"][:3]
    with pytest.raises(ValueError, match="scales"):
        export_ply(tmp_path / "g.ply", params)
    with pytest.raises(FileNotFoundError, match="missing.ply"):
        import_ply(tmp_path / "missing.ply")
    (tmp_path / "ascii.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    with pytest.raises(ValueError, match="not a 3DGS PLY"):
        import_ply(tmp_path / "ascii.ply")


def test_trimesh_reads_the_file(tmp_path):
    """A third-party PLY reader sees the same vertices and properties."""
    import trimesh
    params = _random_params(n=12, k=15, seed=3)
    path = export_ply(tmp_path / "g.ply", params).path
    cloud = trimesh.load(path, file_type="ply")
    np.testing.assert_allclose(np.asarray(cloud.vertices), params["means"].numpy(), rtol=0, atol=0)
