"""One wrapper for every command-line entry point: user errors as one line and exit code 2, bugs with a traceback.

``--debug`` (anywhere on the command line) or ``KC_DEBUG=1`` shows the traceback of a user error too.
"""

from __future__ import annotations

import argparse
import errno
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from kc_splatfacto.errors import UserError

DEBUG_FLAG = "--debug"
DEBUG_ENV = "KC_DEBUG"
USER_ERROR_EXIT = 2
FULL_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


def debug_requested(argv: Sequence[str]) -> bool:
    return DEBUG_FLAG in argv or os.environ.get(DEBUG_ENV, "").strip() not in ("", "0", "false", "no")


def run_cli(prog: str, main: Callable[[list[str]], int], argv: Sequence[str] | None = None) -> int:
    """``main(argv without --debug)``; a :class:`UserError` becomes ``prog: error: message`` on stderr and exit 2."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = debug_requested(argv)
    argv = [a for a in argv if a != DEBUG_FLAG]
    try:
        return main(argv)
    except OSError as exc:
        # a full disk or quota is the machine's state, not a bug: one line naming the file (writes are atomic, so
        # nothing partial is left); any other OSError keeps its traceback
        if debug or exc.errno not in FULL_DISK_ERRNOS:
            raise
        print(f"{prog}: error: could not write {exc.filename or 'a file'} ({exc.strerror}): free space on that disk "
              "and run the command again", file=sys.stderr)
        return USER_ERROR_EXIT
    except UserError as exc:
        if debug:
            raise
        message = " ".join(line.strip() for line in str(exc).splitlines() if line.strip())  # one line
        prefix = f"{prog}: "
        if message.startswith(prefix):  # some messages already name the tool
            message = message[len(prefix):]
        print(f"{prog}: error: {message}", file=sys.stderr)
        return USER_ERROR_EXIT


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """``--load-config`` (required) and ``--step``: how every command that reads a trained run names it."""
    parser.add_argument("--load-config", type=Path, required=True, help="the run's config.yml (or its run folder)")
    parser.add_argument("--step", type=int, default=None, help="checkpoint step (default: the latest)")


def existing_run_config(prog: str, load_config) -> Path:
    """``load_config`` as a Path (a run folder stands for its config.yml); a :class:`UserError` naming ``prog`` when
    it is neither."""
    load_config = Path(load_config)
    if load_config.is_dir():
        if not (load_config / "config.yml").is_file():
            raise UserError(f"{prog}: --load-config {load_config} is a folder without a config.yml: pass a run folder "
                            "or its config.yml")
        load_config = load_config / "config.yml"
    if not load_config.is_file():
        raise UserError(f"{prog}: --load-config {load_config} does not exist (pass a run's config.yml)")
    return load_config


def check_output_path(path, what: str) -> None:
    """The folder of an output file must be writable, and the path not a folder: checked before the (slow) run
    loading."""
    from kc_splatfacto.engine.run_guard import check_writable_folder

    if Path(path).is_dir():
        raise UserError(f"{what} {path} is a folder: pass the path of the file to write (it may be inside that folder)")
    check_writable_folder(Path(path).absolute().parent, f"the folder of {what}")
