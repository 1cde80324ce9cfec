"""`make install`'s TORCH is pip's arguments for torch: a single requirement (quoted for the shell: `torch>=2.5` is no
redirection) or one with pip options, as the README's CPU-build command passes (issue 68)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("torch, expected", [
    (None, 'pip install "torch==2.13.0"'),
    ("torch>=2.5", 'pip install "torch>=2.5"'),
    ("torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu",
     'pip install "torch==2.13.0" --index-url https://download.pytorch.org/whl/cpu'),
])
def test_torch_arguments_reach_pip_as_the_readme_says(torch, expected, tmp_path):
    if shutil.which("make") is None:
        pytest.skip("no make")
    command = ["make", "-n", "install", f"VENV={tmp_path / 'venv'}"] + ([f"TORCH={torch}"] if torch else [])
    out = subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=60, check=True).stdout
    (line,) = [line for line in out.splitlines() if "import torch" in line]
    assert line.rstrip().endswith(expected), line
