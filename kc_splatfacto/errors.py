"""User errors: bad input, a wrong flag, an unusable file. The command-line tools print them as one line and exit 2.

Raise :class:`UserError` (or a subclass) when the *user* can fix the problem; the message names the file or flag and
says what to do. Anything else is a bug and keeps its traceback (see :mod:`kc_splatfacto.cli.main`).
"""

from __future__ import annotations

import importlib
from types import ModuleType


class UserError(Exception):
    """A mistake in the input or the command line; the message names the file or flag and the fix."""


class CheckpointError(UserError, ValueError):
    """A checkpoint that cannot be read (truncated, not a checkpoint) or does not fit the run."""


class ConfigFileError(UserError, ValueError):
    """A ``config.yml`` that cannot be read back (garbage, or objects other than the project's configs)."""


class ConfigFileNotFoundError(ConfigFileError, FileNotFoundError):
    """No ``config.yml`` where one was given."""


class ResumeError(UserError, ValueError):
    """A resume (``--load-dir``) that would not continue the same run."""


class Interrupted(KeyboardInterrupt):
    """A Ctrl-C a tool has cleaned up after: the message says what is left and how to go on (the command-line tools
    print it as one line and exit 130). A KeyboardInterrupt so that code which only lets Ctrl-C through still does."""


def import_optional(module: str, package: str, needed_by: str, install: str) -> ModuleType:
    """``module`` of the optional ``package``, imported for ``needed_by`` (a flag or a tool); a one-line
    :class:`UserError` when the package is not installed (naming ``install``) or is installed but fails to import (a
    broken install, a clash with another package's version: whatever its import raises, named)."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        if exc.name in (package, module):  # the package itself is absent, not one of its own imports
            raise UserError(f"{needed_by} needs the {package} package, which does not import ({exc}): {install}") from exc
        raise _broken_install(package, needed_by, exc) from exc
    except Exception as exc:  # noqa: BLE001  whatever the package's own import raises is its install's fault
        raise _broken_install(package, needed_by, exc) from exc


def _broken_install(package: str, needed_by: str, exc: BaseException) -> UserError:
    first_line = next((line.strip() for line in str(exc).splitlines() if line.strip()), "")
    return UserError(f"{needed_by}: the {package} package is installed but fails to import ({type(exc).__name__}: "
                     f"{first_line}): repair it (pip install --force-reinstall {package}) or run without {needed_by}")
