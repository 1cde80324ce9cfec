"""kc-export on a tiny demo run: the PLY holds the model's Gaussians, and re-importing them renders the same images."""

from __future__ import annotations

import pytest
import torch

from kc_splatfacto.cli import export as kc_export
from kc_splatfacto.engine.run_io import load_run
from kc_splatfacto.model.ply import export_ply, import_ply
from tests._demo_runs import demo_run


@pytest.fixture(scope="module")
def run_config(tmp_path_factory):
    return demo_run(tmp_path_factory)


def _render_all(model, dataset) -> list[torch.Tensor]:
    with torch.no_grad():
        return [model.get_outputs(dataset.cameras[i])["rgb"] for i in range(len(dataset))]


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
