"""Ctrl-C while a tool is still importing torch is one line and exit code 130, as it is later (issue 68): the console
scripts run through kc_splatfacto.cli.launch, which imports nothing heavy.

The interrupt comes at a fixed point, not after a guessed delay: a sitecustomize module (in a temporary folder on
PYTHONPATH; the environment has none of its own) puts an import hook in front that, when the tool's start-up imports
torch, either raises KeyboardInterrupt itself or marks a file and sleeps until the test's SIGINT arrives.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from kc_splatfacto.cli.launch import TOOLS

BIN = Path(sys.executable).parent

HOOK = '''
import os, sys, time

_NAME = os.environ.get("KC_TEST_INTERRUPT_IMPORT")


class _InterruptAtImport:
    """When _NAME is first imported: KeyboardInterrupt, or (KC_TEST_INTERRUPT_READY names a file) that file, then a
    sleep the test's SIGINT ends, with a KeyboardInterrupt from inside the import."""

    def find_spec(self, fullname, path=None, target=None):
        if fullname != _NAME:
            return None
        sys.meta_path.remove(self)
        ready = os.environ.get("KC_TEST_INTERRUPT_READY")
        if ready:
            open(ready, "w").close()
            time.sleep(120)
            raise SystemExit("the SIGINT never came")
        raise KeyboardInterrupt


if _NAME:
    sys.meta_path.insert(0, _InterruptAtImport())
'''


@pytest.fixture(scope="module")
def hook_dir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("interrupt-hook")
    (folder / "sitecustomize.py").write_text(HOOK)
    return folder


def _env(hook_dir: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("KC_DEBUG",)}
    env["PYTHONPATH"] = os.pathsep.join([str(hook_dir), *filter(None, [env.get("PYTHONPATH")])])
    env["KC_TEST_INTERRUPT_IMPORT"] = "torch"
    env.update(extra)
    return env


def _script(tool: str) -> Path:
    script = BIN / tool
    if not script.is_file():
        pytest.skip(f"{script} is not installed (pip install -e .)")
    return script


def _assert_one_interrupt_line(tool: str, result_code: int, err: str) -> None:
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert err.strip().splitlines() == [f"{tool}: interrupted (Ctrl-C)"], err
    assert result_code == 130, err


def test_the_launcher_imports_nothing_heavy():
    code = ("import sys, kc_splatfacto.cli.launch; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('torch', 'numpy', 'numba', 'kc_splatfacto') "
            "and m not in ('kc_splatfacto', 'kc_splatfacto.cli', 'kc_splatfacto.cli.launch')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True).stdout
    assert out.strip() == "[]"


def test_every_console_script_goes_through_the_launcher():
    for tool, function in TOOLS.items():
        text = _script(tool).read_text()
        assert f"from kc_splatfacto.cli.launch import {function.__name__}" in text, (tool, text)


@pytest.mark.parametrize("tool", sorted(TOOLS))
def test_an_interrupt_while_importing_torch_is_one_line_and_exit_130(tool, hook_dir):
    result = subprocess.run([str(_script(tool)), "--help"], env=_env(hook_dir), capture_output=True, text=True,
                            timeout=120)
    _assert_one_interrupt_line(tool, result.returncode, result.stderr)
    assert result.stdout == ""  # it stopped before the help


@pytest.mark.parametrize("tool", sorted(TOOLS))
def test_a_sigint_while_importing_torch_is_one_line_and_exit_130(tool, hook_dir, tmp_path):
    """A real SIGINT (what Ctrl-C sends), delivered once the start-up is inside ``import torch``. The tool starts with
    SIGINT's default action, as from a terminal: a test run started in the background of a non-interactive shell
    (``make test &``, a CI runner's) ignores SIGINT, and Python started with it ignored never raises
    KeyboardInterrupt."""
    ready = tmp_path / "importing-torch"
    process = subprocess.Popen([str(_script(tool)), "--help"], env=_env(hook_dir, KC_TEST_INTERRUPT_READY=str(ready)),
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 60
        while not ready.exists():
            assert process.poll() is None, process.communicate()
            assert time.monotonic() < deadline, "the start-up never reached import torch"
            time.sleep(0.01)
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    _assert_one_interrupt_line(tool, process.returncode, err)
    assert out == ""


def test_with_debug_the_interrupt_keeps_its_traceback(hook_dir):
    result = subprocess.run([str(_script("kc-train")), "--help"], env=_env(hook_dir, KC_DEBUG="1"),
                            capture_output=True, text=True, timeout=120)
    assert "Traceback" in result.stderr and "KeyboardInterrupt" in result.stderr, result.stderr
    assert result.returncode != 0
