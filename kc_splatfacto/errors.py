"""User errors: bad input, a wrong flag, an unusable file. The command-line tools print them as one line and exit 2.

Raise :class:`UserError` (or a subclass) when the *user* can fix the problem; the message names the file or flag and
says what to do. Anything else is a bug and keeps its traceback (see :mod:`kc_splatfacto.cli.main`).
"""

from __future__ import annotations


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
