"""Entry-point discovery of method and dataparser specifications (nerfstudio's ``discover_methods`` pattern).

A third-party package registers its own method in its ``pyproject.toml``::

    [project.entry-points."kc_splatfacto.method_configs"]
    my-method = "my_package.configs:my_method"

where ``my_method`` is a :class:`MethodSpecification`. Extra specifications can also be named at run time, without
installing anything, through environment variables holding comma-separated ``name=module:attribute`` items::

    KC_SPLATFACTO_METHOD_CONFIGS="my-method=my_package.configs:my_method"
    KC_SPLATFACTO_DATAPARSER_CONFIGS="my-format=my_package.data:my_parser"
"""

from __future__ import annotations

import importlib
import os
import sys
import warnings
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from kc_splatfacto.errors import UserError

METHOD_GROUP = "kc_splatfacto.method_configs"
DATAPARSER_GROUP = "kc_splatfacto.dataparser_configs"
METHOD_ENV = "KC_SPLATFACTO_METHOD_CONFIGS"
#: the top-level package this project's own methods install as: the design's ``method_configs/`` folder, beside
#: ``kc_splatfacto/`` in a checkout and in site-packages alike
OWN_METHODS_PACKAGE = "method_configs"
DATAPARSER_ENV = "KC_SPLATFACTO_DATAPARSER_CONFIGS"


@dataclass
class MethodSpecification:
    """A method: the config that builds it, and a one-line description shown by ``kc-train --help``."""

    config: Any
    description: str


@dataclass
class DataParserSpecification:
    """A dataparser: its config (a dataclass with ``setup()``) and a one-line description."""

    config: Any
    description: str


class RegistryError(UserError, RuntimeError):
    """A registered specification could not be loaded or has the wrong type (a plugin's or the environment
    variable's: the message names which, and the tools print it as one line)."""


def _load_object(name: str, target: str, origin: str) -> Any:
    module_name, _, attribute = target.partition(":")
    if not module_name or not attribute:
        raise RegistryError(f"{origin}: '{name}={target}' must have the form name=module:attribute")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise RegistryError(f"{origin}: cannot import module '{module_name}' for '{name}': {exc}") from exc
    except Exception as exc:  # the module itself fails while importing: name it, not a traceback into it
        raise RegistryError(f"{origin}: importing module '{module_name}' for '{name}' failed: "
                            f"{type(exc).__name__}: {exc} (fix or remove it from {origin})") from exc
    try:
        return getattr(module, attribute)
    except AttributeError as exc:
        raise RegistryError(f"{origin}: module '{module_name}' has no attribute '{attribute}' (for '{name}')") from exc


def check_own_methods_package() -> None:
    """``method_configs`` is a generic top-level name that another distribution, or a folder on ``sys.path``, could
    also have: the one imported must be the folder beside this package, never a namesake whose methods would be
    trained under this project's method names."""
    module = sys.modules.get(OWN_METHODS_PACKAGE)
    module_file = getattr(module, "__file__", None)
    if module_file is None:
        return
    ours = Path(__file__).resolve().parents[1] / OWN_METHODS_PACKAGE
    found = Path(module_file).resolve().parent
    if found != ours:
        raise RegistryError(
            f"the '{OWN_METHODS_PACKAGE}' package imported from {found} is not kc-splatfacto's ({ours}): another "
            f"installed package or a folder on sys.path has the same top-level name; uninstall or rename it, or put "
            f"kc-splatfacto first on sys.path"
        )


def _discover(group: str, env_var: str, expected: type) -> dict[str, Any]:
    found: dict[str, Any] = {}
    origins: dict[str, str] = {}  # what each name stands for, as a warning names it
    kind = "method" if group == METHOD_GROUP else "dataparser"
    for ep in entry_points(group=group):
        try:
            spec = ep.load()
        except Exception as exc:  # a broken third-party plugin must name itself
            raise RegistryError(f"entry point '{ep.name}' in group '{group}' ({ep.value}) failed to load: {exc}") from exc
        own = ep.value.split(".")[0].split(":")[0] == OWN_METHODS_PACKAGE
        if own:
            check_own_methods_package()
        if not isinstance(spec, expected):
            raise RegistryError(
                f"entry point '{ep.name}' in group '{group}' ({ep.value}) is a {type(spec).__name__}, "
                f"expected a {expected.__name__}"
            )
        _warn_if_replaced(ep.name, origins, f"the entry point {ep.value}")
        found[ep.name] = spec
        origins[ep.name] = f"the {'built-in ' if own else ''}{kind} '{ep.name}' ({ep.value})"
    for item in filter(None, (s.strip() for s in os.environ.get(env_var, "").split(","))):
        name, sep, target = item.partition("=")
        if not sep:
            raise RegistryError(f"{env_var}: '{item}' must have the form name=module:attribute")
        name, target = name.strip(), target.strip()
        spec = _load_object(name, target, env_var)
        if not isinstance(spec, expected):
            raise RegistryError(f"{env_var}: '{item}' is a {type(spec).__name__}, expected a {expected.__name__}")
        _warn_if_replaced(name, origins, f"{env_var}'s {name}={target}")
        found[name] = spec
        origins[name] = f"the {kind} '{name}' of {env_var} ({target})"
    return dict(sorted(found.items()))


def _warn_if_replaced(name: str, origins: dict[str, str], new: str) -> None:
    """One warning when ``name`` is registered already: the later registration wins, which a user must know (a
    study of 'splatfacto' would otherwise train another method under the built-in's name without a word)."""
    if name in origins:
        warnings.warn(f"{new} replaces {origins[name]}; give it another name to keep both", stacklevel=3)


def discover_methods() -> dict[str, MethodSpecification]:
    """All registered methods, by name: entry points of ``kc_splatfacto.method_configs`` plus ``KC_SPLATFACTO_METHOD_CONFIGS``."""
    return _discover(METHOD_GROUP, METHOD_ENV, MethodSpecification)


def discover_dataparsers() -> dict[str, DataParserSpecification]:
    """All registered dataparsers, by name: entry points of ``kc_splatfacto.dataparser_configs`` plus the env variable."""
    return _discover(DATAPARSER_GROUP, DATAPARSER_ENV, DataParserSpecification)
