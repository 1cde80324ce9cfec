"""kc-export on a tiny demo run: every format holds the model's Gaussians (read back by the readers of
tests/model/test_export_formats.py, written from each format's description), re-importing the PLY renders the same
images, and the user's mistakes (an existing file, a name that says no format, an unwritable folder) are one line."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from kc_splatfacto.cli import export as kc_export
from kc_splatfacto.engine.run_io import load_run
from kc_splatfacto.model.gaussians_ply import export_ply, import_ply
from tests._demo_runs import demo_run
from tests.model.test_export_formats import read_compressed_ply, read_splat, read_spz, sigmoid


@pytest.fixture(scope="module")
def run_config(tmp_path_factory):
    return demo_run(tmp_path_factory)


def _render_all(model, dataset) -> list[torch.Tensor]:
    with torch.no_grad():
        return [model.get_outputs(dataset.cameras[i])["rgb"] for i in range(len(dataset))]


def _one_error_line(capsys) -> str:
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("kc-export: error: "), lines
    return lines[0]


def test_export_reimport_renders_the_same(run_config, tmp_path):
    ply = tmp_path / "splat.ply"
    assert kc_export.entrypoint(["--load-config", str(run_config), "--output-path", str(ply)]) == 0
    original = load_run(run_config)
    params = import_ply(ply)
    for name, value in original.model.gauss_params.items():
        torch.testing.assert_close(params[name], value.detach().reshape(params[name].shape), rtol=0, atol=0)
    reloaded = load_run(run_config)
    reloaded.model.load_gauss_params({k: v.reshape(original.model.gauss_params[k].shape) for k, v in params.items()})
    for a, b in zip(_render_all(original.model, original.test_dataset), _render_all(reloaded.model, original.test_dataset)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_nan_row_dropped_and_rest_renders_the_same(run_config, tmp_path):
    loaded = load_run(run_config)
    state = {k: v.detach().clone() for k, v in loaded.model.gauss_params.items()}
    n = state["means"].shape[0]
    bad = n // 2
    state["means"][bad, 0] = float("nan")
    result = export_ply(tmp_path / "nan.ply", state)
    assert (result.num_written, result.num_dropped) == (n - 1, 1)
    keep = torch.arange(n) != bad
    reference = load_run(run_config)
    reference.model.load_gauss_params({k: v[keep] for k, v in state.items()})
    imported = import_ply(result.path)
    loaded.model.load_gauss_params({k: v.reshape(state[k][keep].shape) for k, v in imported.items()})
    for a, b in zip(_render_all(reference.model, loaded.test_dataset), _render_all(loaded.model, loaded.test_dataset)):
        assert torch.isfinite(b).all()
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_every_format_from_the_file_name(run_config, tmp_path, capsys):
    """The four formats of the same run, the format taken from each name: every Gaussian in each file (the demo
    run's opacities all above 1/255), the positions within each format's quantisation, SH degree 3 kept by the
    compressed formats, and those at least 3x smaller than the PLY."""
    params = load_run(run_config).model.gaussian_state()
    means = params["means"].detach().numpy().astype(np.float64)
    n = means.shape[0]
    assert params["features_rest"].shape[1:] == (15, 3)
    assert (sigmoid(params["opacities"].detach().numpy()) > 1 / 255).all()
    names = {"ply": "s.ply", "splat": "s.splat", "ply-compressed": "s.compressed.ply", "spz": "s.spz"}
    sizes = {}
    for fmt, name in names.items():
        assert kc_export.entrypoint(["--load-config", str(run_config), "--output-path", str(tmp_path / name)]) == 0
        assert f"wrote {n} Gaussians as {fmt}" in capsys.readouterr().out
        sizes[fmt] = (tmp_path / name).stat().st_size
    splat = read_splat((tmp_path / "s.splat").read_bytes())["means"]  # float32 positions, reordered
    np.testing.assert_array_equal(np.unique(splat, axis=0), np.unique(means.astype(np.float32), axis=0))
    compressed = read_compressed_ply((tmp_path / "s.compressed.ply").read_bytes())
    assert compressed["features_rest"].shape == (n, 15, 3)
    # each decoded position within half a quantisation step (of its chunk's range, per axis) of some Gaussian of the
    # run: a nearest-neighbour search in the chunk's step units, in the max norm
    for start in range(0, n, 256):
        half = compressed["means_step"][start] / 2 + 1e-5
        distance, _ = cKDTree(means / half).query(compressed["means"][start:start + 256] / half, p=np.inf)
        assert (distance <= 1).all(), start
    spz = read_spz((tmp_path / "s.spz").read_bytes())  # the run's order: position i is Gaussian i
    assert spz["features_rest"].shape == (n, 15, 3)
    assert spz["flags"] == (load_run(run_config).model.config.rasterize_mode == "antialiased")  # the run's mode
    assert (np.abs(spz["means"] - means) <= 0.5 / 4096 + 1e-7).all()
    for fmt in ("ply-compressed", "spz"):
        assert sizes[fmt] * 3 <= sizes["ply"], sizes


def test_format_flag_and_default_name(run_config, tmp_path, monkeypatch, capsys):
    """Without --output-path the file goes to the run's own RUN/exports/splat.<ending> (issue 68: it went to the
    current folder), which the last line names; --help says so."""
    run = tmp_path / "run"
    shutil.copytree(run_config.parent, run)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    assert kc_export.entrypoint(["--load-config", str(run), "--format", "spz"]) == 0
    assert capsys.readouterr().out.rstrip().endswith(f"-> {run / 'exports' / 'splat.spz'}")
    assert read_spz((run / "exports" / "splat.spz").read_bytes())["means"].shape[1] == 3
    assert not list(elsewhere.iterdir())
    assert kc_export.entrypoint(["--load-config", str(run / "config.yml")]) == 0  # ply without --format
    assert capsys.readouterr().out.rstrip().endswith(f"-> {run / 'exports' / 'splat.ply'}")
    with pytest.raises(SystemExit):
        kc_export.entrypoint(["--help"])
    assert "default: RUN/exports/splat.ply" in " ".join(capsys.readouterr().out.split())
    monkeypatch.chdir(tmp_path)
    # a compressed PLY may end in plain .ply (it is one); any other name takes the format from --format
    for name in ("scene.ply", "scene.bin"):
        assert kc_export.entrypoint(["--load-config", str(run_config), "--format", "ply-compressed",
                                     "--output-path", name]) == 0
        assert b"element chunk" in (tmp_path / name).read_bytes()[:200]


def test_default_folder_that_cannot_be_made_is_one_line_and_nothing_is_created(run_config, tmp_path, capsys):
    """RUN/exports blocked by a file: one line naming it; a run that fails to load leaves no exports folder."""
    run = tmp_path / "run"
    shutil.copytree(run_config.parent, run)
    (run / "exports").write_text("a file, not a folder")
    assert kc_export.entrypoint(["--load-config", str(run)]) == 2
    line = _one_error_line(capsys)
    assert f"the run's exports folder {run / 'exports'} is a file" in line and "--output-path" in line
    (run / "exports").unlink()
    for checkpoint in (run / "nerfstudio_models").iterdir():
        checkpoint.unlink()
    assert kc_export.entrypoint(["--load-config", str(run)]) == 2
    assert "checkpoint" in _one_error_line(capsys)
    assert not (run / "exports").exists()


def test_existing_output_refused_unless_overwrite(run_config, tmp_path, capsys):
    out = tmp_path / "scene.spz"
    out.write_bytes(b"keep me")
    assert kc_export.entrypoint(["--load-config", str(run_config), "--output-path", str(out)]) == 2
    line = _one_error_line(capsys)
    assert str(out) in line and "--overwrite" in line
    assert out.read_bytes() == b"keep me"
    assert kc_export.entrypoint(["--load-config", str(run_config), "--output-path", str(out), "--overwrite"]) == 0
    assert read_spz(out.read_bytes())["means"].shape[1] == 3


def test_undecided_or_contradictory_format_is_one_line(run_config, tmp_path, capsys):
    assert kc_export.entrypoint(["--load-config", str(run_config), "--output-path", str(tmp_path / "scene")]) == 2
    line = _one_error_line(capsys)
    assert "scene" in line and "--format" in line and ".spz" in line
    assert kc_export.entrypoint(["--load-config", str(run_config), "--output-path", str(tmp_path / "scene.ply"),
                                 "--format", "spz"]) == 2
    line = _one_error_line(capsys)
    assert "scene.ply" in line and ".spz" in line
    assert not list(tmp_path.iterdir())


def test_unwritable_folder_is_one_line(run_config, tmp_path, capsys):
    """A folder that cannot be made (a file stands in its place; a read-only folder would not stop root)."""
    blocker = tmp_path / "notes.txt"
    blocker.write_text("a file, not a folder")
    assert kc_export.entrypoint(["--load-config", str(run_config), "--output-path", str(blocker / "s.spz")]) == 2
    line = _one_error_line(capsys)
    assert str(blocker) in line and "writable" in line


def test_write_failure_is_one_line(run_config, tmp_path, capsys, monkeypatch):
    """A folder that passed the check and then fails the write (a full disk): one line naming the file."""
    import kc_splatfacto.model.export as export_module

    def disk_full(path, data):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(export_module, "atomic_write_bytes", disk_full)
    out = tmp_path / "s.splat"
    assert kc_export.entrypoint(["--load-config", str(run_config), "--output-path", str(out)]) == 2
    line = _one_error_line(capsys)
    assert str(out) in line and "No space left" in line
