"""Every user-facing config value checked once per run, before anything is loaded: types, then ranges, one pass.

A value that reaches numpy, torch or a schedule unchecked fails there with a traceback, or worse trains with a
meaningless setting (``refine_every 0``, an SSIM lambda of 2). :func:`validate_config` walks a ``TrainerConfig``:
first every field against its annotation (an ``int`` field holds an int, not a bool or a string: what a hand-edited
``config.yml`` can hold), then every field's range, declared beside the field (:mod:`kc_splatfacto.settings`). The
first violation is a :class:`ConfigValueError` naming the dotted field, the value, its flag and the allowed range, in
one line. The trainer calls it once per run (``Trainer.__init__``), and the ``config.yml`` reader on what it read.
"""

from __future__ import annotations

import dataclasses
import pathlib
import types
import typing
from typing import Any, Literal, Union

import tyro

from kc_splatfacto.errors import UserError
from kc_splatfacto.settings import is_int, is_real, range_violations


class ConfigValueError(UserError, ValueError):
    """A config field holding a value of the wrong type or outside its range."""


def flag(dotted: str) -> str:
    """The command-line flag of a dotted field (a dataparser's fields are flags of its subcommand, unprefixed)."""
    return "--" + dotted.replace("_", "-").removeprefix("pipeline.datamanager.dataparser.")


def check_ranges(config: Any) -> None:
    """Every field's declared range (:func:`kc_splatfacto.settings.setting`, beside the field) and each config's
    rule between fields; a :class:`ConfigValueError` at the first violation."""
    for violation in range_violations(config):
        raise ConfigValueError(f"{violation.name} = {violation.value!r} is not allowed: {flag(violation.name)} must "
                               f"be {violation.allowed}")


# ------------------------------------------------------------------------------------------------ types


def _matches(value: Any, annotation: Any) -> bool:
    """Whether ``value`` fits ``annotation`` (int, float, bool, str, Path, Literal, Optional, tuple[X, ...])."""
    if annotation is Any or isinstance(annotation, typing.TypeVar):
        return True
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _matches(value, typing.get_args(annotation)[0])
    if origin in (Union, types.UnionType):
        return any(_matches(value, arg) for arg in typing.get_args(annotation) if not _hidden_choice(arg))
    if origin is Literal:
        return any(value == choice and type(value) is type(choice) for choice in typing.get_args(annotation))
    if origin in (tuple, list):
        args = typing.get_args(annotation)
        if not isinstance(value, (tuple, list)):
            return False
        if len(args) == 2 and args[1] is Ellipsis or len(args) == 1:
            return all(_matches(v, args[0]) for v in value)
        return len(args) == len(value) and all(_matches(v, a) for v, a in zip(value, args))
    if annotation is type(None) or annotation is None:
        return value is None
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return is_int(value)
    if annotation is float:
        return is_real(value)
    if annotation is str:
        return isinstance(value, str)
    if isinstance(annotation, type) and issubclass(annotation, pathlib.PurePath):
        return isinstance(value, (pathlib.PurePath, str))  # a path given as a string is the same path
    if isinstance(annotation, type):
        return isinstance(value, annotation) or dataclasses.is_dataclass(value)
    return True  # an annotation this checker does not know: left to the code that uses the field


def _hidden_choice(annotation: Any) -> bool:
    """A union member marked ``tyro.conf.Suppress``: tyro's subcommand unions carry a hidden ``None`` that no command
    line can choose (``DataManagerConfig.dataparser`` once the dataparsers are installed), not a value to accept."""
    return typing.get_origin(annotation) is typing.Annotated and any(
        meta is tyro.conf.Suppress for meta in annotation.__metadata__)


def _describe(annotation: Any) -> str:
    text = str(annotation).replace("typing.", "").replace("pathlib.", "").replace("<class '", "").replace("'>", "")
    return text


def check_types(config: Any, prefix: str = "") -> None:
    """Every field of the config tree against its annotation; a :class:`ConfigValueError` naming the first misfit."""
    try:
        hints = typing.get_type_hints(type(config), include_extras=True)
    except Exception:  # noqa: BLE001  a plugin's config whose annotations do not resolve: its own code checks it
        hints = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        name = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_types(value, f"{name}.")
            continue
        annotation = hints.get(f.name)
        if annotation is not None and not _matches(value, annotation):
            raise ConfigValueError(
                f"{name} = {value!r} has the wrong type ({type(value).__name__}): {flag(name)} must be "
                f"{_describe(annotation)}"
            )


def validate_config(config: Any) -> None:
    """Types, then ranges, of every field of a ``TrainerConfig`` (see the module docstring)."""
    check_types(config)
    check_ranges(config)


__all__ = ["ConfigValueError", "check_ranges", "check_types", "flag", "validate_config"]
