"""Host synchronisations of a training step, counted on the CPU as CUDA counts them, and attributed to source lines.

On CUDA, torch's sync debug mode (``torch.cuda.set_sync_debug_mode("warn")``) warns wherever the host waits for the
device: ``c10::cuda::warn_or_error_on_sync`` runs in ``memcpy_and_sync`` (every blocking copy between host and device
memory: ``.item()``/``bool()``/``float()``/``int()`` of a device tensor through ``_local_scalar_dense``, ``.cpu()``,
``.tolist()``, ``.numpy()`` after them, a blocking ``.to(device)`` of a host tensor, ``torch.tensor(data,
device=...)``) and in the stream and device synchronisations that operators whose output size depends on the data
make (``nonzero``, boolean-mask indexing, ``masked_select``, ``unique``, ...). A ``non_blocking`` copy is not
flagged (Copy.cu takes ``cudaMemcpyAsync`` and records an event instead).

:class:`HostSyncDetector` sees the same on the CPU, where nothing waits: a ``TorchDispatchMode`` flags the aten
operators that synchronise on CUDA (:data:`SYNCHRONISING_ATEN`, boolean-mask ``index``/``index_put``), and wrappers
flag the copies, which on the CPU are no-ops that never reach the dispatcher. Which tensors live in host memory on a
CUDA run (the dataset's images, masks and cameras, tensors made from Python or numpy data, and what is computed from
those alone) is tracked, so a read of a host tensor is not counted and a copy of one to the device is.

Each synchronisation is attributed with :func:`source_of` to the innermost frame of the package (``path:line
function``, ``via`` the library frame below it), or to the rasterizer when it happens inside it: on CUDA that is
gsplat's own work, on the CPU the torch reference that stands in for it (``KC_SPLATFACTO_BACKEND=torch``: the
compiled CPU kernels take another route than CUDA). bench_gpu.py lists CUDA's synchronisations with the same
function, so the two lists compare line by line.

    python benchmarks/host_syncs.py [--method kc-splatfacto] [--steps 6]   # the per-step list on the CPU
"""

from __future__ import annotations

import contextlib
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any, Iterator

import torch

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "kc_splatfacto"

#: aten operators that make the host wait on a CUDA device: their result's value or size is needed on the host
SYNCHRONISING_ATEN = frozenset({
    "_local_scalar_dense", "is_nonzero", "nonzero", "masked_select", "unique", "_unique", "_unique2", "unique_dim",
    "unique_consecutive", "unique_dim_consecutive", "equal", "bincount", "histc", "_linalg_check_errors",
})
#: (module under kc_splatfacto, function or None for the whole module): the rasterizer's internals, which gsplat
#: replaces on CUDA; a synchronisation there is the rasterizer's (gsplat's own on CUDA), not the step's
RASTERIZER_CODE = (("render/rasterization.py", "_rasterization_torch"), ("render/rasterization.py", "_rasterization_cpu"),
                   ("render/rasterization.py", "_rasterization_gsplat"), ("render/rasterize_torch.py", None),
                   ("render/projection.py", None), ("render/sh.py", None), ("render/tiles.py", None),
                   ("render/rasterize_cpu.py", None), ("render/project_cpu.py", None))
RASTERIZER = "rasterizer (gsplat on CUDA, the torch reference on the CPU)"
LIBRARIES = ("gsplat", "kornia", "torch")


def _package_path(frame: FrameType) -> str | None:
    path = Path(frame.f_code.co_filename)
    if PACKAGE in path.parents:
        return path.relative_to(PACKAGE).as_posix()
    return None


def source_of(frame: FrameType | None) -> str | None:
    """Where a synchronisation seen with ``frame`` (the innermost Python frame at that moment) comes from:
    :data:`RASTERIZER` when the rasterizer's internals are on the stack, else ``path:line function`` of the innermost
    package frame, with ``via lib`` when a library's code (kornia, gsplat) stood between; None: no package frame
    (the caller's own code, a test)."""
    via = None
    while frame is not None:
        relative = _package_path(frame)
        if relative is not None:
            outer = frame
            while outer is not None:  # the rasterizer's internals anywhere further out: its synchronisation
                rel = _package_path(outer)
                if rel is not None and any(rel == m and f in (None, outer.f_code.co_name) for m, f in RASTERIZER_CODE):
                    return RASTERIZER
                outer = outer.f_back
            where = f"{relative}:{frame.f_lineno} {frame.f_code.co_name}"
            return where + (f" via {via}" if via else "")
        name = frame.f_code.co_filename
        for lib in LIBRARIES:
            if f"/{lib}/" in name and lib != "torch":
                via = lib
                if lib == "gsplat":
                    return RASTERIZER
        frame = frame.f_back
    return None


@dataclass
class Found:
    """What a :class:`HostSyncDetector` saw: synchronisations and asynchronous copies, by (kind, source)."""

    syncs: Counter = field(default_factory=Counter)
    async_copies: Counter = field(default_factory=Counter)

    def ours(self) -> Counter:
        """The synchronisations of package code, the rasterizer's left out."""
        return Counter({k: v for k, v in self.syncs.items() if k[1] != RASTERIZER})

    def clear(self) -> None:
        self.syncs.clear()
        self.async_copies.clear()

    def table(self, steps: int = 1) -> str:
        lines = [f"{v / steps:6.2f}  {kind:28s} {where}" for (kind, where), v in sorted(self.syncs.items(),
                                                                                       key=lambda kv: kv[0][1])]
        lines += [f"{v / steps:6.2f}  {'(async) ' + kind:28s} {where}" for (kind, where), v in
                  sorted(self.async_copies.items(), key=lambda kv: kv[0][1])]
        return "\n".join(lines) or "(none)"


def _tensors(tree: Any) -> Iterator[torch.Tensor]:
    if isinstance(tree, torch.Tensor):
        yield tree
    elif isinstance(tree, (list, tuple)):
        for item in tree:
            yield from _tensors(item)
    elif isinstance(tree, dict):
        for item in tree.values():
            yield from _tensors(item)


def _is_bool_index(indices: Any) -> bool:
    return any(t.dtype == torch.bool for t in _tensors(indices))


class HostSyncDetector:
    """Count, on the CPU, what would make the host wait for a CUDA device (module docstring).

    Args:
        host: tensors that live in host memory on a CUDA run (the datasets' images, masks and cameras); tensors
            computed from host tensors alone are host tensors too, and so is what ``torch.tensor``, ``as_tensor``
            and ``from_numpy`` make without a device.

    A copy's target device is told apart from the host by how the code names it: ``"cpu"`` (a string) is the host,
    a ``torch.device`` or a tensor's device is the training device (on the CPU both are the CPU).
    """

    def __init__(self, host: Any = ()):
        from torch.utils._python_dispatch import TorchDispatchMode
        from torch.utils.weak import WeakTensorKeyDictionary

        self.found = Found()
        self._host = WeakTensorKeyDictionary()
        for t in _tensors(host):
            self._host[t] = True
        detector = self

        class Mode(TorchDispatchMode):
            def __torch_dispatch__(self, func, types, args=(), kwargs=None):
                kwargs = kwargs or {}
                name = func.__name__.split(".")[0]
                inputs = list(_tensors((args, kwargs)))
                out = func(*args, **kwargs)
                host_inputs = [t for t in inputs if detector.is_host(t)]
                if inputs and len(host_inputs) == len(inputs):
                    for t in _tensors(out):  # computed from host tensors alone: in host memory on CUDA too
                        detector._host[t] = True
                elif name in SYNCHRONISING_ATEN:
                    detector._flag(name)
                elif name in ("index", "index_put", "index_put_", "_index_put_impl_") and len(args) > 1 \
                        and _is_bool_index(args[1]):
                    detector._flag(f"{name} with a boolean mask")
                elif name == "masked_fill" and len(args) > 2 and isinstance(args[2], torch.Tensor) \
                        and not detector.is_host(args[2]):
                    detector._flag("masked_fill with a device value")
                elif name == "repeat_interleave" and "Tensor" in func._overloadname \
                        and kwargs.get("output_size") is None:  # the output's size summed on the host
                    detector._flag("repeat_interleave without output_size")
                return out

        self._mode = Mode()
        self._patches: list[tuple[Any, str, Any]] = []

    def is_host(self, tensor: torch.Tensor) -> bool:
        return tensor in self._host

    def _flag(self, kind: str) -> None:
        where = source_of(sys._getframe(2))
        if where is not None:
            self.found.syncs[(kind, where)] += 1

    # --------------------------------------------------------------------------------------------- the wrappers
    def _patch(self, owner: Any, name: str, make) -> None:
        original = getattr(owner, name)
        self._patches.append((owner, name, original))
        setattr(owner, name, make(original))

    def _target(self, args: tuple, kwargs: dict) -> str | None:
        """'host', 'device' or None (no device named: a dtype conversion)."""
        candidates = [kwargs.get("device"), *(a for a in args if isinstance(a, (str, torch.device, torch.Tensor)))]
        for c in candidates:
            if c is None:
                continue
            if isinstance(c, torch.Tensor):
                return "host" if self.is_host(c) else "device"
            if isinstance(c, str):
                return "host" if c.split(":")[0] == "cpu" else "device"
            return "device"
        return None

    def _moved(self, source: torch.Tensor, result: Any, target: str | None, non_blocking: bool) -> Any:
        """The copy a ``.to()``-like call makes on CUDA: flagged, and its result as the device would hold it."""
        if not isinstance(result, torch.Tensor) or target is None:
            return result
        from_host = self.is_host(source)
        if target == "device" and from_host:
            where = source_of(sys._getframe(2))
            if where is not None:
                (self.found.async_copies if non_blocking else self.found.syncs)[("host-to-device copy", where)] += 1
            if result is source:  # a no-op on the CPU: on CUDA a new tensor in device memory
                result = result.clone()
            self._host.pop(result, None)
        elif target == "host" and not from_host:
            where = source_of(sys._getframe(2))
            if where is not None:
                (self.found.async_copies if non_blocking else self.found.syncs)[("device-to-host copy", where)] += 1
            if result is source:
                result = result.clone()
            self._host[result] = True
        return result

    def _install(self) -> None:
        detector = self

        def wrap_to(original):
            def to(self_, *args, **kwargs):
                result = original(self_, *args, **kwargs)
                non_blocking = bool(kwargs.get("non_blocking", False)) or any(a is True for a in args)
                return detector._moved(self_, result, detector._target(args, kwargs), non_blocking)
            return to

        def wrap_cpu(original):
            def cpu(self_, *args, **kwargs):
                return detector._moved(self_, original(self_, *args, **kwargs), "host", False)
            return cpu

        def wrap_cuda(original):
            def cuda(self_, *args, **kwargs):  # never called on the CPU (no CUDA): a device copy if it were
                return detector._moved(self_, self_, "device", bool(kwargs.get("non_blocking", False)))
            return cuda

        def wrap_read(kind):
            def make(original):
                def read(self_, *args, **kwargs):
                    if not detector.is_host(self_):
                        where = source_of(sys._getframe(1))
                        if where is not None:
                            detector.found.syncs[(kind, where)] += 1
                    return original(self_, *args, **kwargs)
                return read
            return make

        def wrap_copy_(original):
            def copy_(self_, src, non_blocking=False):
                if isinstance(src, torch.Tensor) and detector.is_host(src) != detector.is_host(self_):
                    kind = "host-to-device copy" if detector.is_host(src) else "device-to-host copy"
                    where = source_of(sys._getframe(1))
                    if where is not None:
                        (detector.found.async_copies if non_blocking else detector.found.syncs)[(kind, where)] += 1
                return original(self_, src, non_blocking)
            return copy_

        def wrap_factory(original):
            def factory(data, *args, **kwargs):
                result = original(data, *args, **kwargs)
                device = kwargs.get("device")
                if device is None:
                    detector._host[result] = True
                elif not (isinstance(device, str) and device.split(":")[0] == "cpu"):
                    source = data if isinstance(data, torch.Tensor) else None
                    if source is None or detector.is_host(source):
                        where = source_of(sys._getframe(1))
                        if where is not None:
                            detector.found.syncs[("host-to-device copy", where)] += 1
                return result
            return factory

        def wrap_from_numpy(original):
            def from_numpy(array):
                result = original(array)
                detector._host[result] = True
                return result
            return from_numpy

        self._patch(torch.Tensor, "to", wrap_to)
        self._patch(torch.Tensor, "cpu", wrap_cpu)
        self._patch(torch.Tensor, "cuda", wrap_cuda)
        self._patch(torch.Tensor, "copy_", wrap_copy_)
        self._patch(torch.Tensor, "tolist", wrap_read("device-to-host copy (tolist)"))
        self._patch(torch.Tensor, "numpy", wrap_read("device-to-host copy (numpy)"))
        self._patch(torch, "tensor", wrap_factory)
        self._patch(torch, "as_tensor", wrap_factory)
        self._patch(torch, "from_numpy", wrap_from_numpy)

    def _uninstall(self) -> None:
        while self._patches:
            owner, name, original = self._patches.pop()
            setattr(owner, name, original)

    @contextlib.contextmanager
    def counting(self) -> Iterator[Found]:
        """Count within the block (the wrappers and the dispatch mode installed, then removed)."""
        self._install()
        try:
            with self._mode:
                yield self.found
        finally:
            self._uninstall()


def host_tensors_of(trainer) -> list[torch.Tensor]:
    """The tensors a CUDA run keeps in host memory: the datasets' images, masks and cameras."""
    out: list[torch.Tensor] = []
    for dataset in (trainer.datamanager.train_dataset, trainer.datamanager.eval_dataset):
        for i in range(len(dataset)):
            item = dataset[i]
            out += [item["image"], *([item["mask"]] if "mask" in item else [])]
        cameras = dataset.cameras
        out += [cameras.viewmats, cameras.Ks, cameras.widths, cameras.heights]
    return out


def count_ordinary_steps(trainer, steps: list[int], warm: int = 2) -> Found:
    """The synchronisations of ``trainer.train_iteration`` over ``steps`` (ordinary steps: the caller picks no
    logging, evaluation, refinement or parameter-scan step), on the torch path (the compiled CPU kernels forced
    off: on CUDA gsplat and torch ops run instead). The first ``warm`` of them are taken but not counted: the torch
    path's caches (the DWT's index maps, built once per size and device) fill there, as a CUDA run's do in its
    first steps."""
    from kc_splatfacto import backend

    detector = HostSyncDetector(host_tensors_of(trainer))
    with backend.torch_reference():
        for i, step in enumerate(steps):
            with detector.counting() if i >= warm else contextlib.nullcontext():
                if not trainer.train_iteration(step):
                    raise RuntimeError(f"step {step} was skipped: not an ordinary step")
    return detector.found


def main() -> int:
    import argparse
    import tempfile

    sys.path.insert(0, str(ROOT))
    from kc_splatfacto.engine.trainer import Trainer
    from tests.training_utils import tiny_demo_config

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", default="kc-splatfacto")
    parser.add_argument("--steps", type=int, default=6)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        config = tiny_demo_config(args.method, Path(tmp), iterations=42 + args.steps, steps_scale=1.0)
        config.logging.steps_per_log = 1000
        config.logging.steps_per_gradient_shares = 0
        trainer = Trainer(config)
        trainer.setup()
        for step in range(30):
            trainer.train_iteration(step)
        found = count_ordinary_steps(trainer, list(range(30, 32 + args.steps)))
    print(f"{args.method}: host synchronisations per ordinary step on the torch path ({args.steps} steps)")
    print(found.table(args.steps))
    return 0


if __name__ == "__main__":
    sys.exit(main())
