"""Every ``>>>`` example in the library runs and prints what its docstring says (kornia's style: an example that
runs). The modules are found by their source, so a new example is collected without being listed here."""

from __future__ import annotations

import doctest
import importlib
import warnings
from pathlib import Path

import pytest

import kc_splatfacto
from kc_splatfacto.data.base import CACHE_ENV

PACKAGE = Path(kc_splatfacto.__file__).parent
NEEDS_NERFSTUDIO = "nerfstudio_plugin"  # imports nerfstudio, which only its own environment has (make test-nerfstudio)


def modules_with_examples() -> list[str]:
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE.parent).with_suffix("")
        if NEEDS_NERFSTUDIO in relative.parts or ">>> " not in path.read_text(encoding="utf-8"):
            continue
        found.append(".".join(relative.parts))
    return found


def test_the_examples_are_found():
    assert {"kc_splatfacto.losses.frequency", "kc_splatfacto.engine.training_state"} <= set(modules_with_examples())


@pytest.mark.parametrize("name", modules_with_examples())
def test_the_examples_run(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # an example that writes (a demo scene's cache) writes here
    monkeypatch.setenv(CACHE_ENV, str(tmp_path / "cache"))
    module = importlib.import_module(name)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an example's small image warns about its DWT levels: not the point here
        result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.attempted > 0 and result.failed == 0, f"{name}: {result.failed} of {result.attempted} failed"
