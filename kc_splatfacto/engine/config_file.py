"""A run's ``config.yml``: written by :func:`save_config`, read back by :func:`read_config_file` without running code
from it.

The reader is told which config class the file must hold (``read_config_file(path, TrainerConfig)``): it imports no
config class of its own, so it sits below the trainer that writes and reads these files
(:func:`kc_splatfacto.engine.config.load_config` is the ``TrainerConfig`` reading).

``config.yml`` is PyYAML's object dump of the run's :class:`~kc_splatfacto.engine.trainer.TrainerConfig`. Reading it
with ``yaml.Loader`` would import any module and call any function a ``!!python/...`` tag names: a config file someone
sent could run arbitrary code. :class:`ConfigLoader` is PyYAML's ``SafeLoader`` plus exactly the tags the dump holds:

- ``!!python/object:MODULE.CLASS`` where CLASS is a dataclass of kc_splatfacto (or of a package that registered a
  method or dataparser through the entry points): rebuilt through its ``__init__`` from plain values;
- ``!!python/object/apply:pathlib.PosixPath`` (and the other pathlib classes): ``Path(*parts)``;
- ``!!python/tuple``.

Every other tag is a :class:`~kc_splatfacto.errors.ConfigFileError` naming the file and line, and so is a key the
config class has no field for (with a did-you-mean). A config class whose fields moved since earlier files were
written reads them through its ``upgrade_fields(fields: dict) -> dict`` classmethod (the model config's frequency-loss
settings, once model fields, now nested in ``frequency``), before that check. The rebuilt config then goes through
:func:`kc_splatfacto.engine.validation.validate_config`: a value of the wrong type or out of range names the file and
the dotted field.
"""

from __future__ import annotations

import dataclasses
import difflib
import importlib
import pathlib
from pathlib import Path
from typing import Any, TypeVar

import yaml

from kc_splatfacto.atomic import atomic_write_text
from kc_splatfacto.engine.validation import ConfigValueError, validate_config
from kc_splatfacto.errors import ConfigFileError, ConfigFileNotFoundError
from kc_splatfacto.registry import (
    DataParserSpecification,
    MethodSpecification,
    discover_dataparsers,
    discover_methods,
)

ConfigT = TypeVar("ConfigT")

PROJECT_PACKAGE = "kc_splatfacto"
PATH_CLASSES = ("PosixPath", "WindowsPath", "PurePosixPath", "PureWindowsPath", "Path")
OBJECT_TAG = "tag:yaml.org,2002:python/object:"
APPLY_TAG = "tag:yaml.org,2002:python/object/apply:"
TUPLE_TAG = "tag:yaml.org,2002:python/tuple"


class ConfigLoader(yaml.SafeLoader):
    """SafeLoader that also rebuilds the project's config dataclasses, paths and tuples (nothing else)."""

    source = "<config>"


def _where(loader: ConfigLoader, node: yaml.Node) -> str:
    return f"{loader.source}:{node.start_mark.line + 1}"


def _registered_packages() -> set[str]:
    """Top-level packages of every registered method's and dataparser's config dataclasses (plugins included)."""
    roots: set[str] = set()

    def walk(value: Any, depth: int = 0) -> None:
        if depth > 8 or not dataclasses.is_dataclass(value) or isinstance(value, type):
            return
        roots.add(type(value).__module__.split(".")[0])
        for f in dataclasses.fields(value):
            walk(getattr(value, f.name, None), depth + 1)

    specs: list[MethodSpecification | DataParserSpecification] = [*discover_methods().values(),
                                                                  *discover_dataparsers().values()]
    for spec in specs:
        walk(spec.config)
    return roots


def _allowed_class(loader: ConfigLoader, suffix: str, node: yaml.Node) -> type:
    module_name, _, class_name = suffix.rpartition(".")
    root = module_name.split(".")[0]
    if root != PROJECT_PACKAGE and root not in _registered_packages():
        raise ConfigFileError(
            f"{_where(loader, node)}: '!!python/object:{suffix}' is not a kc-splatfacto config class; refusing to "
            "import it (a config file must not run code): use the config.yml a kc-splatfacto run wrote"
        )
    try:
        cls = getattr(importlib.import_module(module_name), class_name)
    except (ImportError, AttributeError) as exc:
        raise ConfigFileError(f"{_where(loader, node)}: config class {suffix} does not exist ({exc})") from exc
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise ConfigFileError(f"{_where(loader, node)}: {suffix} is not a config dataclass; refusing to build it")
    return cls


def _construct_dataclass(loader: ConfigLoader, suffix: str, node: yaml.Node) -> Any:
    cls = _allowed_class(loader, suffix, node)
    if not isinstance(node, yaml.MappingNode):
        raise ConfigFileError(f"{_where(loader, node)}: {suffix} must be a mapping of its fields")
    key_nodes = {key.value: key for key, _ in node.value if isinstance(key, yaml.ScalarNode)}
    state = loader.construct_mapping(node, deep=True)
    upgrade = getattr(cls, "upgrade_fields", None)
    if callable(upgrade):  # a file written by an earlier version, whose fields this class has since moved
        state = upgrade(dict(state))
    init_fields = {f.name for f in dataclasses.fields(cls) if f.init}
    for key in state:  # an unknown key is a typo or another version's field: never silently dropped
        if key not in init_fields:
            close = difflib.get_close_matches(str(key), sorted(init_fields), n=1)
            hint = f" (did you mean '{close[0]}'?)" if close else ""
            raise ConfigFileError(
                f"{_where(loader, key_nodes.get(key, node))}: {cls.__name__} has no field '{key}'{hint}: fix or "
                f"remove that line (its fields: {', '.join(sorted(init_fields))})"
            )
    try:
        return cls(**state)
    except Exception as exc:  # noqa: BLE001  a __post_init__ refusing a value, a missing required field
        raise ConfigFileError(f"{_where(loader, node)}: cannot build {suffix} from its fields: {exc}") from exc


def _construct_apply(loader: ConfigLoader, suffix: str, node: yaml.Node) -> Any:
    module_name, _, name = suffix.rpartition(".")
    if module_name.split(".")[0] != "pathlib" or name not in PATH_CLASSES:
        raise ConfigFileError(
            f"{_where(loader, node)}: '!!python/object/apply:{suffix}' would call a function while reading the "
            "config; refusing it (only pathlib paths are allowed)"
        )
    parts = loader.construct_sequence(node, deep=True) if isinstance(node, yaml.SequenceNode) else []
    if not all(isinstance(p, str) for p in parts):
        raise ConfigFileError(f"{_where(loader, node)}: a path must be a list of strings, got {parts!r}")
    return getattr(pathlib, name)(*parts) if parts else getattr(pathlib, name)()


def _construct_tuple(loader: ConfigLoader, node: yaml.Node) -> tuple:
    return tuple(loader.construct_sequence(node, deep=True))


def _refuse(loader: ConfigLoader, suffix: str, node: yaml.Node) -> Any:
    raise ConfigFileError(
        f"{_where(loader, node)}: tag '{node.tag}' is not allowed in a kc-splatfacto config (it could run code)"
    )


ConfigLoader.add_multi_constructor(OBJECT_TAG, _construct_dataclass)
ConfigLoader.add_multi_constructor(APPLY_TAG, _construct_apply)
ConfigLoader.add_constructor(TUPLE_TAG, _construct_tuple)
ConfigLoader.add_multi_constructor("tag:yaml.org,2002:python/", _refuse)
ConfigLoader.add_multi_constructor("!", _refuse)


def load_yaml(text: str, source: str = "<config>") -> Any:
    """Parse ``text`` with :class:`ConfigLoader`; ``source`` names the file in errors."""
    loader_class = type("BoundConfigLoader", (ConfigLoader,), {"source": source})
    try:
        return yaml.load(text, Loader=loader_class)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" (line {mark.line + 1}: {getattr(exc, 'problem', None) or 'parse error'})" if mark else ""
        raise ConfigFileError(f"{source} is not valid YAML{where}: pass the config.yml a run wrote") from exc


def save_config(config: Any, path: Path) -> None:
    """Write a run's full config (a ``TrainerConfig``) as YAML (PyYAML's object dump, as nerfstudio writes it),
    atomically."""
    atomic_write_text(path, yaml.dump(config, Dumper=yaml.Dumper, sort_keys=False))


def missing_fields(path: Path | str, config: Any) -> list[str]:
    """Dotted names of the fields of ``config`` (as read from ``path``) that the file has no line for: the reader
    fills them with their defaults, so a line lost in an edit (or a field newer than the file) shows only here."""
    node = yaml.compose(Path(path).read_text(encoding="utf-8"), Loader=ConfigLoader)
    return _missing_in(node, config, "")


def _missing_in(node: Any, value: Any, prefix: str) -> list[str]:
    if not (dataclasses.is_dataclass(value) and not isinstance(value, type) and isinstance(node, yaml.MappingNode)):
        return []
    children = {key.value: child for key, child in node.value if isinstance(key, yaml.ScalarNode)}
    found = []
    for f in dataclasses.fields(value):
        if not f.init:
            continue
        if f.name not in children:
            found.append(f"{prefix}{f.name}")
        else:
            found += _missing_in(children[f.name], getattr(value, f.name), f"{prefix}{f.name}.")
    return found


def check_lines_kept(path: Path | str, config: Any, involved: dict[str, Any], trouble: str) -> None:
    """A :class:`ConfigFileError` when ``path`` (read as ``config``) has no line for a field of ``involved`` (dotted
    name: the value it should hold, or None when unknown): ``trouble`` (what went wrong) came from that field's
    default, not from another run."""
    lost = [name for name in missing_fields(path, config) if name in involved]
    if not lost:
        return
    used = ", ".join(f"{name} (its default {_dotted(config, name)!r} was used)" for name in lost)
    restore = "; ".join(_restore_line(name, involved[name]) for name in lost)
    raise ConfigFileError(f"{path} is incomplete (edited by hand, or written by an older version?): it has no line for {used}, and so {trouble}: "
                          f"{restore}")


def check_method_name(path: Path | str, method_name: str, written_by: Any) -> None:
    """A :class:`ConfigFileError` blaming ``method_name`` in ``path`` when it is no registered method while the
    checkpoint beside it was written by ``written_by`` (the recorded method): a name misspelt in an edit, not a
    checkpoint of another run."""
    try:
        methods = discover_methods()
    except Exception:  # noqa: BLE001  a broken plugin: its own command says so; the caller's message stands
        return
    if not methods or method_name in methods or not isinstance(written_by, str) or written_by == method_name:
        return
    close = difflib.get_close_matches(method_name, list(methods), n=1)
    hint = f" (did you mean {close[0]}?)" if close else ""
    raise ConfigFileError(
        f"{path}: method_name {method_name!r} is not a registered method{hint}, and the run's checkpoint was written "
        f"by {written_by!r}: put back 'method_name: {written_by}' in that file"
    )


def _dotted(value: Any, name: str) -> Any:
    for part in name.split("."):
        value = getattr(value, part, None)
    return value


def _restore_line(name: str, value: Any) -> str:
    parent, _, leaf = name.rpartition(".")
    line = f"'{leaf}: {value}'" if value is not None else f"the '{leaf}:' line (the run's value)"
    return f"put back {line}" + (f" under {parent}" if parent else "")


def read_config_file(path: Path | str, config_type: type[ConfigT]) -> ConfigT:
    """The ``config_type`` instance stored in ``path`` (a run's ``config.yml`` holds a ``TrainerConfig``), its fields'
    types and ranges checked; a :class:`ConfigFileError` naming the file when it holds anything else."""
    path = Path(path)
    if not path.is_file():
        raise ConfigFileNotFoundError(f"config file {path} not found: pass the config.yml of a run folder")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigFileError(f"config file {path} cannot be read ({exc})") from exc
    config = load_yaml(text, str(path))
    if not isinstance(config, config_type):
        raise ConfigFileError(
            f"{path} does not hold a kc-splatfacto {config_type.__name__} (found {type(config).__name__}): pass the "
            "config.yml of a run folder"
        )
    try:
        validate_config(config)
    except ConfigValueError as exc:
        raise ConfigFileError(f"{path}: {exc}; fix that value in the file") from exc
    return config
