"""Host synchronisations in an ordinary training step (no logging, evaluation, density-control refinement or
parameter scan: those may synchronise, every N steps), counted on the CPU as torch's CUDA sync debug mode counts
them (benchmarks/host_syncs.py: synchronising aten operators at the dispatcher, blocking copies between host and
device memory, reads of device scalars; host-memory tensors such as the dataset's cameras tracked, so reading them
is no synchronisation). The step runs on the torch path, the one a GPU takes (the compiled CPU kernels forced off);
the rasterizer's own synchronisations are gsplat's on CUDA and are left out."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest
import torch

from kc_splatfacto.engine import training_state
from kc_splatfacto.engine.trainer import Trainer
from tests.conftest import PROJECT_ROOT
from tests.training_utils import tiny_demo_config

SPEC = importlib.util.spec_from_file_location("host_syncs", PROJECT_ROOT / "benchmarks" / "host_syncs.py")
host_syncs = importlib.util.module_from_spec(SPEC)
sys.modules["host_syncs"] = host_syncs  # dataclasses look their module up while the class is built
SPEC.loader.exec_module(host_syncs)

#: the synchronisations an ordinary step keeps, each with why (by kind and 'module function', lines left out), by
#: where the step's verdict is taken (machine.step_verdict)
KEPT = {
    # whether the step is good (render, loss and gradients reduced to one flag on the device), read before the update
    "host": {("_local_scalar_dense", "engine/training_state.py reason"): 1},
    # the flag goes to fused Adam as found_inf and is read at the next log, evaluation or checkpoint (CUDA's default)
    "device": {},
}


def _by_function(counts, steps: int) -> dict:
    """{(kind, 'module function[ via lib]'): per step} from the detector's 'module:line function[ via lib]'."""
    out: dict = {}
    for (kind, where), n in counts.items():
        module, _, rest = where.partition(":")
        key = (kind, f"{module} {rest.split(' ', 1)[1]}" if ":" in where else where)
        out[key] = out.get(key, 0) + n / steps
    return out


def _warm_trainer(method: str, tmp_path, step_verdict: str = "host") -> Trainer:
    config = tiny_demo_config(method, tmp_path, iterations=50, steps_scale=1.0)
    config.machine.step_verdict = step_verdict
    config.logging.steps_per_log = 1000
    config.logging.steps_per_gradient_shares = 0
    trainer = Trainer(config)
    trainer.setup()
    for step in range(30):  # caches, the GT's wavelet statistics, the first step's one-time work
        trainer.train_iteration(step)
    return trainer


@pytest.mark.parametrize("step_verdict", ["host", "device"])
@pytest.mark.parametrize("method", ["splatfacto", "kc-splatfacto", "kc-splatfacto-corr"])
def test_an_ordinary_step_keeps_at_most_the_step_verdict(method, step_verdict, tmp_path):
    trainer = _warm_trainer(method, tmp_path, step_verdict)
    steps = list(range(30, 38))
    assert all(s % training_state.PARAMETER_SCAN_EVERY for s in steps)
    found = host_syncs.count_ordinary_steps(trainer, steps, warm=2)
    counted = len(steps) - 2
    assert _by_function(found.ours(), counted) == KEPT[step_verdict]
    # the step's copies from host memory are asynchronous (pinned on CUDA): the image and the camera's two matrices
    assert _by_function(found.async_copies, counted) == {("host-to-device copy", "model/splatfacto.py host_to_device"): 3}
    # the count is not blind inside the step: the torch rasterizer (gsplat on CUDA) synchronises, and is seen
    assert any(where == host_syncs.RASTERIZER for _, where in found.syncs)


def _package_function(code: str):
    """A function compiled as if it were package code (its frames carry a path under kc_splatfacto/)."""
    namespace = {"torch": torch, "np": np}
    exec(compile(code, str(host_syncs.PACKAGE / "model" / "probe.py"), "exec"), namespace)
    return namespace["probe"]


def test_the_detector_sees_what_synchronises_on_cuda_and_not_what_does_not():
    """Each kind the detector counts, written in package code, on a device tensor and on a host tensor."""
    probe = _package_function(
        "def probe(x, host, mask):\n"
        "    a = float(x.sum())\n"                       # a device scalar read: _local_scalar_dense
        "    b = x[mask]\n"                              # a boolean-mask index: nonzero inside
        "    c = x.nonzero()\n"
        "    d = x.tolist()\n"                           # device to host
        "    e = x.cpu()\n"
        "    f = host.to(x.device)\n"                    # host to device, blocking
        "    g = host.to(x.device, non_blocking=True)\n"  # asynchronous: not flagged by CUDA
        "    h = torch.tensor([1.0, 2.0], device=x.device)\n"  # Python data to the device
        "    i = int(host[0])\n"                         # a host read: no synchronisation
        "    j = torch.where(mask, x, 0.0).sum()\n"      # masked arithmetic: none
        "    k = torch.as_tensor(np.arange(3.0)).tolist()\n"  # host data read on the host: none
        "    return a, b, c, d, e, f, g, h, i, j, k\n")
    host = torch.arange(4.0)
    detector = host_syncs.HostSyncDetector(host=[host])
    with detector.counting() as found:
        probe(torch.arange(4.0) + 1, host, torch.tensor([True, False, True, False]))
    kinds = sorted(kind for kind, _ in found.syncs.elements())
    assert kinds == sorted(["_local_scalar_dense", "index with a boolean mask", "nonzero", "device-to-host copy (tolist)",
                            "device-to-host copy", "host-to-device copy", "host-to-device copy"])
    assert [kind for kind, _ in found.async_copies] == ["host-to-device copy"]
    assert all(where.startswith("model/probe.py:") for _, where in found.syncs)
    # what the caller's own code does is not the package's: not counted
    detector.found.clear()
    with detector.counting() as found:
        float((torch.arange(4.0) + 1).sum())
    assert not found.syncs


def test_the_rasterizers_internals_are_told_apart():
    """A synchronisation with the torch rasterizer's functions on the stack is the rasterizer's (gsplat's on CUDA);
    elsewhere it is the innermost package frame's."""
    def here():
        return host_syncs.source_of(sys._getframe())

    assert here() is None  # a test is not package code
    package_code = _package_function("def probe(f):\n    return f()\n")
    assert package_code(here) == "model/probe.py:2 probe"
    namespace: dict = {}
    exec(compile("def _rasterization_torch(f):\n    return f()\n", str(host_syncs.PACKAGE / "render" / "rasterization.py"),
                 "exec"), namespace)
    assert namespace["_rasterization_torch"](lambda: package_code(here)) == host_syncs.RASTERIZER
