"""The plugin on a GPU (skipped without CUDA, i.e. everywhere but a lent GPU machine): nerfstudio's own Splatfacto path
(gsplat 1.4's CUDA rasterizer, torchmetrics' LPIPS when its weights can be had) with the three terms, whose values
for the same render and ground truth match the CPU's to float32 rounding; and a short ``ns-train`` on CUDA."""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("nerfstudio", reason="nerfstudio is not installed here: run `make test-nerfstudio`")
if not torch.cuda.is_available():
    pytest.skip("no CUDA device here (these run on a lent GPU machine)", allow_module_level=True)

from tests.conftest import shared_scene  # noqa: E402
from tests.nerfstudio_plugin.test_cli import CPU_RUN, STEPS, loss_terms, ns  # noqa: E402
from tests.nerfstudio_plugin.test_model import TERMS, _inputs  # noqa: E402


def test_the_three_terms_on_cuda_equal_the_cpus():
    from kc_splatfacto.losses.frequency import FrequencyLossConfig

    pred, batch = _inputs()
    frequency_loss = FrequencyLossConfig().setup()
    values = {}
    for device in ("cpu", "cuda"):
        gt = (batch["image"].float() / 255).permute(2, 0, 1)[None].to(device)
        terms = frequency_loss(pred.detach().permute(2, 0, 1)[None].to(device), frequency_loss.prepare_target(gt))
        values[device] = {t: float(terms[t]) for t in TERMS}
    for term in TERMS:
        assert values["cuda"][term] == pytest.approx(values["cpu"][term], rel=1e-4), term


def test_ns_train_on_cuda_has_the_three_terms(tmp_path):
    cuda_run = [arg if arg != "cpu" else "cuda" for arg in CPU_RUN]
    ns("ns-train", "kc-splatfacto", *cuda_run, "--output-dir", str(tmp_path), "--max-num-iterations", str(STEPS),
       "--data", str(shared_scene("castle-P30")), "spars3r", "--downscale-factor", "4", cwd=tmp_path)
    terms = loss_terms(tmp_path / "castle-P30" / "kc-splatfacto" / "run")
    assert all(max(terms[t]) > 0 for t in TERMS)
