"""The render layer's error for NaN/inf inputs (no numba import here: the torch backend raises it too)."""

from __future__ import annotations

import torch
from torch import Tensor


class NonFiniteInputError(ValueError):
    """A rasterization input holds NaN/inf. ``fields`` names the arguments found so (the message names the first
    one and its count of non-finite values)."""

    def __init__(self, message: str, fields: tuple[str, ...] = ()):
        super().__init__(message)
        self.fields = fields


def non_finite_message(name: str, tensor: Tensor) -> str:
    """The message for argument ``name``: how many of its values are NaN/inf, and the fix."""
    bad = int((~torch.isfinite(tensor.detach())).sum())
    return f"rasterization: {name} holds {bad} NaN/inf value(s); fix the parameters (or their optimizer)"
