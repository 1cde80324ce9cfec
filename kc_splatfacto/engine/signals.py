"""Stop requests: SIGINT (Ctrl-C) and SIGTERM (``timeout``, ``kill``, job schedulers) both end training cleanly.

The trainer's handler finishes the current step, saves a checkpoint and returns; a second signal aborts at once.
Handlers can only be installed from the main thread; elsewhere (a trainer run in a worker thread) nothing changes.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable

STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM") if hasattr(signal, name))


def install_stop_handlers(handler: Callable) -> dict | None:
    """Route SIGINT and SIGTERM to ``handler(signum, frame)``; returns the previous handlers (None off the main
    thread, where Python allows no handler)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return {sig: signal.signal(sig, handler) for sig in STOP_SIGNALS}


def current_stop_handlers() -> dict | None:
    """The handlers SIGINT and SIGTERM have now, for :func:`restore_handlers` (None off the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return {sig: signal.getsignal(sig) for sig in STOP_SIGNALS}


def restore_handlers(previous: dict | None) -> None:
    """Put back what :func:`install_stop_handlers` replaced (or what :func:`current_stop_handlers` saw)."""
    for sig, old in (previous or {}).items():
        signal.signal(sig, old)
