"""Host synchronisations in a training step (issue 36): every call that makes the host wait for a CUDA device
(``.item()``, ``bool()``/``float()``/``int()`` of a tensor, ``.tolist()``, ``nonzero``, a boolean-mask index,
``.cpu()``), counted on the CPU by wrapping those calls while kc-train's trainer takes ordinary steps: no logging,
evaluation, density-control refinement or parameter scan among them (those may synchronise, every N steps).

What only the CPU runs is left out of the count: the compiled CPU kernels' modules (the rasterizer's CPU backend,
the ``_*_kernels`` modules) and the ``.numpy()`` calls that hand tensors to them (a CUDA tensor has no ``.numpy()``).
Density control's statistics are counted on the torch path, the one a GPU runs (the CPU takes a compiled pass)."""

from __future__ import annotations

import sys
from collections import Counter
from pathlib import Path

import pytest
import torch

import kc_splatfacto
from kc_splatfacto.engine import trainer as trainer_module
from kc_splatfacto.engine.trainer import Trainer
from kc_splatfacto.model import strategy
from tests.training_utils import tiny_demo_config

PACKAGE = Path(kc_splatfacto.__file__).parent
CPU_ONLY = ("render/rasterize_cpu.py", "render/project_cpu.py", "render/tiles.py")
TENSOR_CALLS = ("item", "__bool__", "__float__", "__int__", "__index__", "tolist", "nonzero", "cpu")
TORCH_CALLS = ("nonzero", "masked_select", "unique")
#: reads of tensors that live in host memory whatever the training device, so no synchronisation on a GPU
HOST_TENSORS = {
    ("__int__", "model/splatfacto.py:get_outputs"): "the camera's width and height: Cameras stay in host memory",
}


def _caller() -> str | None:
    """'module.py:function' of the first caller outside torch, when it is package code that runs on a GPU."""
    frame = sys._getframe(2)
    while frame is not None and "/torch/" in frame.f_code.co_filename:
        frame = frame.f_back
    if frame is None:
        return None
    path = Path(frame.f_code.co_filename)
    if PACKAGE not in path.parents:
        return None
    relative = path.relative_to(PACKAGE).as_posix()
    if relative in CPU_ONLY or path.name.startswith("_") and path.name.endswith("_kernels.py"):
        return None
    return f"{relative}:{frame.f_code.co_name}"


@pytest.fixture
def count_syncs(monkeypatch):
    counts: Counter = Counter()

    def wrap(owner, name):
        original = getattr(owner, name)

        def counted(*args, **kwargs):
            where = _caller()
            if where is not None:
                counts[(name, where)] += 1
            return original(*args, **kwargs)

        monkeypatch.setattr(owner, name, counted)

    for name in TENSOR_CALLS:
        wrap(torch.Tensor, name)
    for name in TORCH_CALLS:
        wrap(torch, name)
    where = torch.where

    def counted_where(*args, **kwargs):  # torch.where(mask): nonzero() by another name
        if len(args) + len(kwargs) == 1 and _caller() is not None:
            counts[("torch.where(mask)", _caller())] += 1
        return where(*args, **kwargs)

    monkeypatch.setattr(torch, "where", counted_where)
    getitem = torch.Tensor.__getitem__

    def masked_getitem(self, index):  # x[mask]: a nonzero() inside
        parts = index if isinstance(index, tuple) else (index,)
        if any(isinstance(p, torch.Tensor) and p.dtype == torch.bool for p in parts):
            where = _caller()
            if where is not None:
                counts[("bool-mask index", where)] += 1
        return getitem(self, index)

    monkeypatch.setattr(torch.Tensor, "__getitem__", masked_getitem)
    return counts


@pytest.mark.parametrize("method", ["splatfacto", "kc-splatfacto", "kc-splatfacto-corr"])
def test_an_ordinary_training_step_synchronises_once(method, tmp_path, monkeypatch, count_syncs):
    config = tiny_demo_config(method, tmp_path, iterations=40, steps_scale=1.0)
    config.logging.steps_per_log = 1000
    config.logging.steps_per_gradient_shares = 0
    config.logging.progress_bar = True  # lines every 100 steps: none among the counted ones
    trainer = Trainer(config)
    trainer.setup()
    for step in range(30):  # warm: caches, the GT's wavelet statistics, the first step's one-time work
        trainer.train_iteration(step)
    monkeypatch.setattr(strategy, "_stats_kernel_applies", lambda *args: False)  # the GPU's torch path
    count_syncs.clear()
    steps = range(30, 36)
    assert all(s % trainer_module.PARAMETER_SCAN_EVERY for s in steps)
    for step in steps:
        assert trainer.train_iteration(step)  # a good step
    per_step = {k: v / len(steps) for k, v in count_syncs.items() if k not in HOST_TENSORS}
    # the one left: whether the step is good (render, loss and gradients, reduced to one flag on the device)
    assert per_step == {("__bool__", "engine/trainer.py:_step_problem"): 1.0}


def test_the_count_sees_a_synchronisation(tmp_path, count_syncs):
    """The wrapping itself: a float() of a loss in package code is counted (the check above cannot pass by seeing
    nothing)."""
    from kc_splatfacto.engine.trainer import StepLosses

    losses = StepLosses({"main_loss": torch.tensor(0.5)})
    assert losses["loss"] == 0.5
    assert count_syncs[("tolist", "engine/trainer.py:_read")] == 1


#: aten operators that make the host wait on a CUDA device (their results' size or value is needed on the host)
SYNCHRONISING_ATEN = ("_local_scalar_dense", "nonzero", "nonzero_static", "masked_select", "unique", "_unique",
                      "_unique2", "unique_dim", "unique_consecutive", "equal", "is_nonzero", "bincount", "histc",
                      "multinomial")


class _AtenSyncCount:
    """A second, independent count below the Python API: every synchronising aten operator and every boolean-mask
    ``index`` that reaches torch's dispatcher, by the package function that called it (``_caller``'s rules)."""

    def __init__(self) -> None:
        from torch.utils._python_dispatch import TorchDispatchMode

        counts: Counter = Counter()

        class Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                name = func.__name__.split(".")[0]
                masked = name == "index" and len(args) > 1 and any(
                    isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in args[1] if i is not None)
                if name in SYNCHRONISING_ATEN or masked:
                    where = _package_frame()
                    if where is not None:
                        counts[(name, where)] += 1
                return func(*args, **(kwargs or {}))

        self.counts, self.mode = counts, Mode()


def _package_frame() -> str | None:
    """'module.py:function' of the innermost package frame that runs on a GPU (None: none, or CPU-only code)."""
    frame = sys._getframe(1)
    while frame is not None:
        path = Path(frame.f_code.co_filename)
        if PACKAGE in path.parents:
            relative = path.relative_to(PACKAGE).as_posix()
            if relative in CPU_ONLY or path.name.startswith("_") and path.name.endswith("_kernels.py"):
                return None
            return f"{relative}:{frame.f_code.co_name}"
        frame = frame.f_back
    return None


@pytest.mark.parametrize("method", ["splatfacto", "kc-splatfacto"])
def test_the_dispatcher_sees_the_same_single_synchronisation(method, tmp_path, monkeypatch):
    """The same ordinary steps counted at torch's dispatcher (TorchDispatchMode) instead of by wrapping Python calls:
    a synchronising call the wrapping misses (an operator reached another way) would show here. The first GPU campaign
    reported 54 and 25 synchronisations per step; its window held a run's last step (evaluation and checkpoint)."""
    config = tiny_demo_config(method, tmp_path, iterations=40, steps_scale=1.0)
    config.logging.steps_per_log = 1000
    config.logging.steps_per_gradient_shares = 0
    trainer = Trainer(config)
    trainer.setup()
    for step in range(30):
        trainer.train_iteration(step)
    monkeypatch.setattr(strategy, "_stats_kernel_applies", lambda *args: False)
    count = _AtenSyncCount()
    with count.mode:
        for step in range(30, 36):
            assert trainer.train_iteration(step)
    per_step = {k: v / 6 for k, v in count.counts.items()}
    host_reads = {k: v for k, v in per_step.items() if k == ("_local_scalar_dense", "model/splatfacto.py:get_outputs")}
    assert host_reads == {("_local_scalar_dense", "model/splatfacto.py:get_outputs"): 2.0}  # width, height (host)
    assert {k: v for k, v in per_step.items() if k not in host_reads} == {
        ("_local_scalar_dense", "engine/trainer.py:_step_problem"): 1.0}


def test_the_dispatcher_count_sees_an_item_and_a_mask_index(monkeypatch):
    """The dispatcher count itself (the check above cannot pass by seeing nothing): ``.item()`` in package code is
    counted, and so is a boolean-mask index. Device-to-host copies (``.tolist()``, ``.cpu()``) are no operators on
    the CPU: this count cannot see them, the wrapping count above does."""
    from kc_splatfacto.metrics import _check_mask

    count = _AtenSyncCount()
    with count.mode:
        _check_mask(torch.ones(1, 1, 4, 4), torch.zeros(1, 3, 4, 4))
        picked = torch.arange(4.0)[torch.tensor([True, False, True, False])]
    assert count.counts[("_local_scalar_dense", "metrics.py:_check_mask")] == 1
    assert picked.tolist() == [0.0, 2.0]
    assert not any(name == "index" for name, _ in count.counts)  # test code is not package code: not counted
    monkeypatch.setattr(sys.modules[__name__], "_package_frame", lambda: "anywhere")
    with count.mode:
        torch.arange(4.0)[torch.tensor([True, False, True, False])]
        torch.arange(4.0)[torch.tensor([0, 2])]  # an integer index needs no synchronisation
    assert count.counts[("index", "anywhere")] == 1
