"""The objects nerfstudio's entry points name (``pyproject.toml``: groups ``nerfstudio.method_configs`` and
``nerfstudio.dataparser_configs``), e.g. ``kc_splatfacto`` for ``ns-train kc-splatfacto``.

nerfstudio loads every plugin's entry point without a try/except, in every ``ns-*`` command: a plugin that raises
there breaks nerfstudio for every method. So importing this module does nothing (it imports no nerfstudio module: the
dataparser entry points are loaded while nerfstudio's own data manager module is half imported, when importing its
trainer would close a circle), and its attributes are built on first access (PEP 562's module ``__getattr__``), one
entry-point group at a time, inside one try per group. When a part the plugin needs is missing or broken, every name
still resolves, to a stand-in that lists as usual and, once chosen on the command line, stops with one line that says
what failed and what to install (nerfstudio's ``ExternalMethodDummyTrainerConfig`` does the same for methods that are
not installed).
"""

from __future__ import annotations

import functools
import importlib.metadata
import sys
from dataclasses import dataclass
from typing import Any

import tyro  # the stand-ins' annotations name it (resolved in this module's globals)

METHODS, DATAPARSERS = "nerfstudio.method_configs", "nerfstudio.dataparser_configs"
INSTALL = "pip install 'kc-splatfacto[nerfstudio]'"
SUPPORTED = "nerfstudio 1.1.5"

_building_stand_ins = False
"""True while this module builds its stand-ins, which must not stop the command that lists them"""


def registered_names(group: str) -> dict[str, str]:
    """{attribute of this module: entry-point name} of this module's entry points in ``group``."""
    found = {}
    for entry in importlib.metadata.entry_points(group=group):
        module, _, attribute = entry.value.partition(":")
        if module.strip() == __name__:
            found[attribute.strip()] = entry.name
    return found


def stop_unless_listing(what: str, reason: str) -> None:
    """Exit with one line, unless this module is building the stand-in: tyro calls ``__init__`` (hence
    ``__post_init__``) on the subcommand the user chose, and only on that one."""
    if not _building_stand_ins:
        sys.exit(f"kc-splatfacto: {what} is unavailable: {reason}")


# ----------------------------------------------------------------------------------------------- the real objects
def _methods() -> dict[str, Any]:
    from kc_splatfacto.nerfstudio_plugin.configs import method_specifications

    by_name = method_specifications()
    missing = sorted(set(registered_names(METHODS).values()) - set(by_name))
    if missing:
        raise LookupError(f"the entry points {missing} name no method of the project's method_configs")
    return {attribute: by_name[name] for attribute, name in registered_names(METHODS).items()}


def _dataparsers() -> dict[str, Any]:
    from kc_splatfacto.nerfstudio_plugin.dataparser import spars3r

    by_name = {"spars3r": spars3r}
    return {attribute: by_name[name] for attribute, name in registered_names(DATAPARSERS).items()}


# ----------------------------------------------------------------------------------------------- stand-ins
@functools.lru_cache(maxsize=None)
def _stand_in_class(group: str) -> type:
    """The config class of a stand-in for ``group`` (its nerfstudio base imported only now, when it is safe)."""
    if group == METHODS:
        from nerfstudio.engine.trainer import TrainerConfig

        @dataclass
        class UnavailableMethodConfig(TrainerConfig):
            """A kc-splatfacto method whose plugin could not be built."""

            reason: tyro.conf.Suppress[str] = ""

            def __post_init__(self) -> None:
                stop_unless_listing(f"ns-train {self.method_name}", self.reason)

        return UnavailableMethodConfig

    from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig

    @dataclass
    class UnavailableDataParserConfig(DataParserConfig):
        """A kc-splatfacto dataparser whose plugin could not be built."""

        name: tyro.conf.Suppress[str] = ""
        reason: tyro.conf.Suppress[str] = ""

        def __post_init__(self) -> None:
            stop_unless_listing(f"the dataparser {self.name}", self.reason)

    return UnavailableDataParserConfig


def _stand_ins(group: str, reason: str) -> dict[str, Any]:
    global _building_stand_ins
    description = f"[kc-splatfacto, unavailable] {reason}"
    config_class = _stand_in_class(group)
    built: dict[str, Any] = {}
    _building_stand_ins = True
    try:
        for attribute, name in registered_names(group).items():
            if group == METHODS:
                from nerfstudio.plugins.types import MethodSpecification

                built[attribute] = MethodSpecification(config_class(method_name=name, reason=reason), description)
            else:
                from nerfstudio.plugins.registry_dataparser import DataParserSpecification

                built[attribute] = DataParserSpecification(config_class(name=name, reason=reason), description)
    finally:
        _building_stand_ins = False
    return built


# ----------------------------------------------------------------------------------------------- access
def failure_reason(exc: BaseException) -> str:
    """One line: the exception's type and first line, which nerfstudio the plugin supports, how to reinstall."""
    text = str(exc).strip()
    first_line = text.splitlines()[0] if text else ""
    return f"{type(exc).__name__}: {first_line} (the plugin supports {SUPPORTED}; reinstall with: {INSTALL})"


@functools.lru_cache(maxsize=None)
def specifications(group: str) -> dict[str, Any]:
    """{attribute: MethodSpecification or DataParserSpecification} of ``group``: the plugin's, or stand-ins."""
    try:
        return _methods() if group == METHODS else _dataparsers()
    except Exception as exc:  # noqa: BLE001  (anything raised here would break every ns-* command)
        return _stand_ins(group, failure_reason(exc))


def __getattr__(attribute: str) -> Any:
    if not attribute.startswith("__"):
        for group in (DATAPARSERS, METHODS):
            if attribute in registered_names(group):
                return specifications(group)[attribute]
    raise AttributeError(f"module {__name__!r} has no attribute {attribute!r}")
