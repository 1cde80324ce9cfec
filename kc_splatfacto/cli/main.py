"""One wrapper for every command-line entry point: user errors as one line and exit code 2, Ctrl-C (or SIGTERM) as
one line and exit code 130, bugs with a traceback.

``--debug`` (anywhere on the command line) or ``KC_DEBUG=1`` shows the traceback of a user error too.
"""

from __future__ import annotations

import argparse
import difflib
import errno
import os
import re
import signal
import sys
import threading
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

# the console scripts' launcher (which says Ctrl-C during the imports) holds the debug switch and the exit code
from kc_splatfacto.cli.launch import DEBUG_FLAG, INTERRUPTED_EXIT, debug_requested
from kc_splatfacto.engine.run_guard import check_writable_folder
from kc_splatfacto.errors import Interrupted, UserError

USER_ERROR_EXIT = 2
FULL_DISK_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


def run_cli(prog: str, main: Callable[[list[str]], int], argv: Sequence[str] | None = None) -> int:
    """``main(argv without --debug)``; a :class:`UserError` becomes ``prog: error: message`` on stderr and exit 2, a
    Ctrl-C ``prog: interrupted (Ctrl-C)...`` and exit 130 (an :class:`Interrupted` adds what is left)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = debug_requested(argv)
    argv = [a for a in argv if a != DEBUG_FLAG]
    shown = warnings.showwarning
    if not debug:  # a warning is one line for the user (`prog: warning: ...`), not a file:line and a source line
        warnings.showwarning = _one_line_warning(prog)
    terminated: list[int] = []
    previous_term = _term_as_interrupt(terminated)
    try:
        return main(argv)
    except UserError as exc:  # first: a user error may also be an OSError (CheckpointNotFoundError)
        if debug:
            raise
        message = " ".join(line.strip() for line in str(exc).splitlines() if line.strip())  # one line
        prefix = f"{prog}: "
        if message.startswith(prefix):  # some messages already name the tool
            message = message[len(prefix):]
        print(f"{prog}: error: {message}", file=sys.stderr)
        return USER_ERROR_EXIT
    except KeyboardInterrupt as exc:
        if debug:
            raise
        detail = " ".join(str(exc).split()) if isinstance(exc, Interrupted) else ""
        how = "SIGTERM" if terminated else "Ctrl-C"
        print(f"{prog}: interrupted ({how}){': ' + detail if detail else ''}", file=sys.stderr, flush=True)
        return INTERRUPTED_EXIT
    except OSError as exc:
        # a full disk or quota is the machine's state, not a bug: one line naming the file (writes are atomic, so
        # nothing partial is left); any other OSError keeps its traceback
        if debug or exc.errno not in FULL_DISK_ERRNOS:
            raise
        print(f"{prog}: error: could not write {exc.filename or 'a file'} ({exc.strerror}): free space on that disk "
              "and run the command again", file=sys.stderr)
        return USER_ERROR_EXIT
    finally:
        warnings.showwarning = shown
        if previous_term is not None:
            signal.signal(signal.SIGTERM, previous_term)


def _term_as_interrupt(received: list[int]):
    """SIGTERM (``kill``, ``timeout``, a job scheduler) ends a tool as Ctrl-C does, where it would otherwise kill the
    process without a word (exit 143): a KeyboardInterrupt, which the tools clean up after, then one line and exit
    130. Installed only over the default handler, on the main thread (a tool that handles SIGTERM itself, as
    kc-train's loop does, keeps its own); returns the handler to put back, or None when none was installed."""
    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "SIGTERM"):
        return None
    if signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL:
        return None

    def interrupt(signum, frame):  # noqa: ARG001
        received.append(signum)
        raise KeyboardInterrupt

    return signal.signal(signal.SIGTERM, interrupt)


def _one_line_warning(prog: str) -> Callable[..., None]:
    def show(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ARG001
        text = " ".join(str(message).split())
        kind = "" if category in (UserWarning, RuntimeWarning) else f" ({category.__name__})"
        print(f"{prog}: warning{kind}: {text}", file=file or sys.stderr)

    return show


#: how many close names a "did you mean" offers, and how close they must be (difflib's ratio)
SUGGESTIONS = 3
SUGGESTION_CUTOFF = 0.6
SUGGESTION_SPREAD = 0.08


def did_you_mean(word: str, valid) -> str:
    """``"; did you mean X or Y?"`` for the names of ``valid`` closest to ``word``, or ``""`` when none is close.

    A flag is scored against the whole valid name and against its last dotted part (``--kc-weigth`` ->
    ``--pipeline.model.frequency.kc-weight``); only names about as close as the best one are offered."""
    scores = {}
    for name in set(valid):
        tail = f"--{name.rsplit('.', 1)[-1].lstrip('-')}" if name.startswith("--") else name
        scores[name] = max(difflib.SequenceMatcher(None, word, name).ratio(),
                           difflib.SequenceMatcher(None, word, tail).ratio())
    ranked = sorted((s, n) for n, s in scores.items() if s >= SUGGESTION_CUTOFF)[::-1]
    close = [n for s, n in ranked if s >= ranked[0][0] - SUGGESTION_SPREAD][:SUGGESTIONS] if ranked else []
    return f"; did you mean {' or '.join(close)}?" if close else ""


class ArgumentParser(argparse.ArgumentParser):
    """argparse whose errors are a :class:`UserError` of one line with the closest valid names (exit 2 through
    :func:`run_cli`, no usage block): ``unrecognized arguments: --fsp; did you mean --fps?``."""

    def error(self, message: str):
        hint = ""
        unknown = re.match(r"unrecognized arguments: (\S+)", message)
        choice = re.match(r"argument [^:]+: invalid choice: '([^']*)'", message)
        if unknown:
            flags = [o for parser in _parser_tree(self) for action in parser._actions for o in action.option_strings
                     if o.startswith("--")]
            hint = did_you_mean(unknown.group(1).split("=", 1)[0], flags)
        elif choice:
            choices = [c for action in self._actions if action.choices for c in action.choices]
            hint = did_you_mean(choice.group(1), [str(c) for c in choices])
        raise UserError(f"{message}{hint} (see {self.prog} --help)")


def _parser_tree(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """``parser`` and its subcommands' parsers (argparse reports a subcommand's unknown flag at the top)."""
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found.extend(_parser_tree(sub))
    return found


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


def path_flag(flag: str, value, default=None) -> str:
    """How a message names a path option: ``--flag VALUE``, or ``--flag's default VALUE`` when it is the default (a
    user who never typed the flag should not read it as theirs)."""
    is_default = default is not None and value is not None and Path(value) == Path(default)
    return f"{flag}'s default {value}" if is_default else f"{flag} {value}"


def check_folder_can_hold(folder, named: str, flag: str) -> None:
    """``folder`` (``named`` in messages, set by ``flag``) must be a folder or creatable as one, by this user: checked
    before any work, without creating it (an error later would leave an empty folder behind)."""
    folder = Path(folder).absolute()
    existing = next(p for p in (folder, *folder.parents) if p.exists())
    if existing == folder and not folder.is_dir():
        raise UserError(f"{named} is a file, not a folder: choose a folder with {flag}")
    if not existing.is_dir():
        raise UserError(f"{named} cannot be created: {existing} is a file, not a folder; choose another with {flag}")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise UserError(f"{named} cannot be {'written' if existing == folder else 'created'}: {existing} is not "
                        f"writable by you; choose another with {flag}")


def check_output_path(path, what: str, default=None) -> None:
    """The folder of an output file must be writable, and the path not a folder: checked before the (slow) run
    loading. ``default``: the flag's default, named as such."""
    named = path_flag(what, path, default)
    if Path(path).is_dir():
        raise UserError(f"{named} is a folder: pass {what} with the path of the file to write (it may be inside that "
                        "folder)")
    where = f"the folder of {what}" if named == f"{what} {path}" else f"the folder of {named}:"
    check_writable_folder(Path(path).absolute().parent, where, f"pass {what} with a path in a folder you can write to")
