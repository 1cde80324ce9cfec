"""The one backend switch (kc_splatfacto.backend): forcing the torch reference reaches every compiled fast path."""

from __future__ import annotations

import pytest
import torch

from kc_splatfacto import backend
from kc_splatfacto.errors import UserError
from kc_splatfacto.render import rasterization, resolve_rasterizer


def test_compiled_only_for_cpu_tensors_and_not_when_forced(monkeypatch):
    monkeypatch.delenv(backend.ENV_VAR, raising=False)
    cpu = torch.zeros(2)
    meta = torch.zeros(2, device="meta")  # a non-CPU device that exists everywhere
    assert backend.compiled(cpu) and not backend.compiled(cpu, meta)
    with backend.torch_reference():
        assert not backend.compiled(cpu) and backend.reference_forced()
        with backend.torch_reference(False):
            assert backend.compiled(cpu)
        assert not backend.compiled(cpu)
    assert backend.compiled(cpu)
    monkeypatch.setenv(backend.ENV_VAR, "torch")
    assert not backend.compiled(cpu)
    with backend.torch_reference(False):  # the context manager wins over the environment
        assert backend.compiled(cpu)


def test_bad_environment_value_is_a_user_error(monkeypatch):
    monkeypatch.setenv(backend.ENV_VAR, "cuda")
    with pytest.raises(UserError, match="KC_SPLATFACTO_BACKEND='cuda' is not a backend"):
        backend.compiled(torch.zeros(1))


def test_forced_reference_makes_auto_rasterize_with_torch():
    cpu = torch.device("cpu")
    with backend.torch_reference():
        assert resolve_rasterizer("auto", cpu) == "torch"
        assert resolve_rasterizer("cpu", cpu) == "cpu"  # an explicit backend is honoured
    assert resolve_rasterizer("auto", cpu) == "cpu"
    n = 5
    g = torch.Generator().manual_seed(0)
    args = (
        torch.randn(n, 3, generator=g) * 0.3 + torch.tensor([0.0, 0.0, 3.0]),
        torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) * 0.2 + 0.05, torch.rand(n, generator=g),
        torch.rand(n, 3, generator=g), torch.eye(4)[None], torch.tensor([[[30.0, 0, 16], [0, 30.0, 12], [0, 0, 1]]]),
        32, 24,
    )
    with backend.torch_reference():
        forced, _, meta_forced = rasterization(*args)
    fast, _, meta_fast = rasterization(*args)
    assert meta_forced["rasterizer"] == "torch" and meta_fast["rasterizer"] == "cpu"
    assert forced.amax() > 0.05  # the scene is on screen
    torch.testing.assert_close(forced, fast, atol=1e-5, rtol=0)
