"""The one switch between the compiled CPU kernels (numba) and the torch reference.

Every compiled fast path (rasterizer projection, tile binning and compositing; density control's screen statistics;
fused D-SSIM; the wavelet levels, moments and band L1) asks :func:`compiled` whether it may run; each path then
checks only what its kernel supports (dtype, layout, options). CUDA tensors never take a compiled CPU kernel: they
run gsplat (``render.rasterization``) or the torch ops.

The torch reference can be forced everywhere, for tests and debugging: ``KC_SPLATFACTO_BACKEND=torch`` in the
environment, or :func:`torch_reference` as a context manager. The results then differ from the
compiled ones by float rounding only (the tests hold each kernel to its reference).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import torch

from kc_splatfacto.errors import UserError

#: environment variable read on every decision: "auto" (default) or "torch" (force the reference)
ENV_VAR = "KC_SPLATFACTO_BACKEND"
CHOICES = ("auto", "torch")


#: set by :func:`torch_reference`; None: the environment decides
_override: bool | None = None


def reference_forced() -> bool:
    """Whether the torch reference is forced (:func:`torch_reference`, else the environment variable)."""
    if _override is not None:
        return _override
    value = os.environ.get(ENV_VAR, "").strip().lower() or "auto"
    if value not in CHOICES:
        raise UserError(f"{ENV_VAR}={os.environ[ENV_VAR]!r} is not a backend: set it to one of {CHOICES} or unset it")
    return value == "torch"


def compiled(*tensors: torch.Tensor) -> bool:
    """Whether the compiled CPU kernels may run for ``tensors``: all on the CPU and the reference not forced."""
    return all(t.device.type == "cpu" for t in tensors) and not reference_forced()


@contextlib.contextmanager
def torch_reference(enabled: bool = True) -> Iterator[None]:
    """Within the block, every fast path runs its torch reference (``enabled=False``: the compiled kernels again)."""
    global _override
    previous = _override
    _override = enabled
    try:
        yield
    finally:
        _override = previous
