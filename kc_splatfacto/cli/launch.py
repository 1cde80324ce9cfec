"""The console scripts' targets ([project.scripts]): each imports its tool's module and runs its ``entrypoint`` inside
``try/except KeyboardInterrupt``, so that Ctrl-C is one line and exit code 130 from the first moment, imports
included (a tool's module imports torch, numba and the rest at module level: seconds before
:func:`kc_splatfacto.cli.main.run_cli`, which says the same once it runs, has its handler).

Nothing here, nor in the packages above it, imports more than the standard library's os and sys.
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Sequence

DEBUG_FLAG = "--debug"
DEBUG_ENV = "KC_DEBUG"
INTERRUPTED_EXIT = 130  # 128 + SIGINT, what a shell reports for a command Ctrl-C ended


def debug_requested(argv: Sequence[str]) -> bool:
    """``--debug`` anywhere on the command line, or ``KC_DEBUG`` set to anything but '', 0, false, no."""
    return DEBUG_FLAG in argv or os.environ.get(DEBUG_ENV, "").strip() not in ("", "0", "false", "no")


def launch(prog: str, module: str) -> int:
    """``module.entrypoint()`` (``kc_splatfacto.cli.<module>``); a Ctrl-C before its own handler holds (while the
    module imports) or after it lets go: ``prog: interrupted (Ctrl-C)`` on stderr and exit 130, as run_cli does
    (with ``--debug`` / ``KC_DEBUG=1``, the traceback)."""
    try:
        return importlib.import_module(f"kc_splatfacto.cli.{module}").entrypoint()
    except KeyboardInterrupt:
        if debug_requested(sys.argv[1:]):
            raise
        print(f"{prog}: interrupted (Ctrl-C)", file=sys.stderr, flush=True)
        return INTERRUPTED_EXIT


def kc_train() -> int:
    return launch("kc-train", "train")


def kc_eval() -> int:
    return launch("kc-eval", "eval")


def kc_render() -> int:
    return launch("kc-render", "render")


def kc_export() -> int:
    return launch("kc-export", "export")


def kc_bench() -> int:
    return launch("kc-bench", "bench")


def kc_process_data() -> int:
    return launch("kc-process-data", "process_data")


def kc_viewer() -> int:
    return launch("kc-viewer", "viewer")


TOOLS = {"kc-train": kc_train, "kc-eval": kc_eval, "kc-render": kc_render, "kc-export": kc_export,
         "kc-bench": kc_bench, "kc-process-data": kc_process_data, "kc-viewer": kc_viewer}
"""every console script and its function here (pyproject.toml's [project.scripts])"""
