"""kc-train's command line as a person meets it: the flags a method's config takes (tyro's names, read off the
config dataclasses), tyro's error boxes as one line with the closest valid names, and a method's help that fits on a
screen (``--help-all`` is tyro's full text).

tyro's naming, which :func:`config_flags` follows: a nested dataclass field is a dotted prefix
(``--pipeline.model.frequency.kc-weight``), underscores become hyphens, a field whose type is a union of dataclasses is a
subcommand whose fields keep the prefix (``--optimizers.means.scheduler.lr-final``), except the dataparser's, whose
subcommands drop it (``colmap --downscale-factor 4``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import re
import sys
import textwrap
import types
import typing
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from kc_splatfacto.cli.main import did_you_mean
from kc_splatfacto.data.detect import AutoDataParserConfig
from kc_splatfacto.errors import UserError
from kc_splatfacto.registry import discover_dataparsers

#: the dataparser subcommand field (its subcommands' flags have no prefix) and where it sits in a TrainerConfig
DATAPARSER_FIELD = "pipeline.datamanager.dataparser"
#: the flags a method's short help explains, one group each (the rest are listed by name)
SHORT_HELP_GROUPS = (
    ("run", ("--data", "--max-num-iterations", "--output-dir", "--load-dir", "--steps-per-eval-all-images",
             "--machine.device", "--machine.seed")),
    ("model", ("--pipeline.model.steps-scale", "--pipeline.model.sh-degree", "--pipeline.model.max-num-gaussians",
               "--pipeline.model.frequency.wavelet-weight", "--pipeline.model.frequency.kc-weight", "--pipeline.model.frequency.cbc-weight",
               "--pipeline.model.frequency.wave", "--pipeline.model.frequency.wavelet-levels",
               "--pipeline.model.rasterizer")),
    ("scene plan", ("--pipeline.model.plan", "--pipeline.model.plan-skip", "--plan-only")),
)
SHORT_HELP_FLAGS = tuple(name for _, names in SHORT_HELP_GROUPS for name in names)
#: flags of kc-train itself, not of the config (``cli/train.py`` reads them): (metavar, help)
COMMAND_FLAGS = {"--plan-only": ("", "print the scene plan and stop (trains nothing)")}
#: flags of earlier versions and where their setting lives now (the frequency-loss settings moved into
#: ``pipeline.model.frequency``, the rasterizer's name was rasterization-backend): named in the error, so an old command
#: line says what to type
MOVED_FLAGS = {
    f"--pipeline.model.{name}": f"--pipeline.model.frequency.{name}"
    for name in ("wavelet-weight", "kc-weight", "cbc-weight", "wave", "wavelet-levels", "wavelet-mode",
                 "wavelet-weighting", "kc-supervised", "cbc-supervised", "cbc-correlation")
} | {"--pipeline.model.rasterization-backend": "--pipeline.model.rasterizer", "--pipeline.datamanager.data": "--data"}
#: help lines the short help words differently from the field's docstring
SHORT_HELP_TEXT = {
    "--data": "scene folder (SPARS3R, COLMAP, transforms.json), or 'demo'",
    "--pipeline.model.plan": "'on': fit to the scene, 'off': the paper's recipe",
    "--pipeline.model.plan-skip": "decisions kept as configured",
}
#: fields the short help does not name one by one: learning rates and schedules (named by group), fields a method
#: fixes
SHORT_HELP_HIDDEN_PREFIXES = ("optimizers.", "method-name", "timestamp")
#: the short help's width and flag column
SHORT_HELP_WIDTH = 110
FLAG_COLUMN = 46
#: tyro's box drawing (rich's, or its ASCII fallback): the sides, and what its top, bottom and rules are made of
BOX_SIDES = "│|"
BOX_RULES = "╭╮╰╯─-+="


SCENE_FLAG = "--data"
"""the scene: the dataparser's ``data``, also accepted among the method's options (:func:`move_scene_flag`)"""


def subcommand_index(argv: list[str], dataparsers: Collection[str]) -> int:
    """Where the dataparser subcommand sits in ``METHOD [OPTIONS] [DATAPARSER ...]`` (``len(argv)`` when none): the
    first dataparser name that is not a flag's value (every flag of kc-train takes a value: ``--data demo`` names a
    scene, not the ``demo`` subcommand)."""
    return next((i for i, arg in enumerate(argv) if i > 0 and arg in dataparsers and not argv[i - 1].startswith("--")),
                len(argv))


def move_scene_flag(argv: list[str], dataparsers: Collection[str]) -> list[str]:
    """``--data SCENE`` given among the method's options (``kc-train METHOD --data SCENE ...``) is the dataparser's
    ``data`` flag: moved behind the dataparser subcommand (``auto`` when none is named), where tyro reads it. The
    config holds the scene in that one field."""
    split = subcommand_index(argv, dataparsers)
    head, tail = argv[:split], argv[split:]
    kept: list[str] = []
    scene: list[str] = []
    i = 0
    while i < len(head):
        if head[i] == SCENE_FLAG and i + 1 < len(head):
            scene, i = [SCENE_FLAG, head[i + 1]], i + 2
        elif head[i].startswith(SCENE_FLAG + "="):
            scene, i = [head[i]], i + 1
        else:
            kept.append(head[i])
            i += 1
    if not scene:
        return argv
    subcommand, rest = (tail[:1], tail[1:]) if tail else (["auto"], [])
    return kept + subcommand + scene + rest


def check_no_moved_flags(args: list[str]) -> None:
    """A :class:`UserError` naming the first flag of ``args`` that moved (:data:`MOVED_FLAGS`) and its new name."""
    for arg in args:
        name = arg.split("=", 1)[0]
        if name in MOVED_FLAGS:
            raise UserError(f"{name} is now {MOVED_FLAGS[name]}")


@dataclass
class Flag:
    """One command-line flag: ``--name``, a metavar (INT, FLOAT, {a,b}, ...), its default and help line."""

    name: str
    metavar: str
    default: Any
    help: str


def _strip_annotated(tp: Any) -> Any:
    while typing.get_origin(tp) is typing.Annotated:
        tp = typing.get_args(tp)[0]
    return tp


def _union_members(tp: Any) -> list[Any]:
    tp = _strip_annotated(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return [_strip_annotated(t) for t in typing.get_args(tp)]
    return []


def _metavar(tp: Any) -> str:
    tp = _strip_annotated(tp)
    members = _union_members(tp)
    if members:
        return "|".join("{None}" if m is type(None) else _metavar(m) for m in members)
    if typing.get_origin(tp) is typing.Literal:
        return "{" + ",".join(str(a) for a in typing.get_args(tp)) + "}"
    if typing.get_origin(tp) in (tuple, list):
        inner = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return f"{_metavar(inner[0]) if inner else 'STR'} ..."
    return {bool: "{True,False}", int: "INT", float: "FLOAT", str: "STR", Path: "PATH"}.get(tp, "VALUE")


def _docstring(cls: type, name: str) -> str:
    try:
        from tyro._docstrings import get_field_docstring  # the docstring below a field, as tyro shows it

        return " ".join((get_field_docstring(cls, name, ()) or "").split())
    except Exception:  # a private tyro helper: its absence costs the help line, nothing else
        return ""


def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls, include_extras=True)
    except Exception:
        return {f.name: f.type for f in dataclasses.fields(cls)}


def _default_instance(cls: type) -> Any:
    try:
        return cls()
    except TypeError:
        return None


def config_flags(config: Any, prefix: str = "") -> list[Flag]:
    """The flags of the dataclass ``config`` (not the dataparser subcommand's: :func:`dataparser_flags`), in field
    order, with tyro's names."""
    flags: list[Flag] = []
    cls = type(config)
    hints = _hints(cls)
    for f in dataclasses.fields(config):
        if not f.init:
            continue
        path = f"{prefix}{f.name.replace('_', '-')}"
        if f"{prefix}{f.name}".replace("_", "-") == DATAPARSER_FIELD.replace("_", "-"):
            continue
        value = getattr(config, f.name)
        members = [m for m in _union_members(hints.get(f.name)) if isinstance(m, type) and dataclasses.is_dataclass(m)]
        if members:  # a subcommand: every member's fields, under this field's prefix
            for member in members:
                instance = value if isinstance(value, member) else _default_instance(member)
                if instance is not None:
                    flags.extend(config_flags(instance, f"{path}."))
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            flags.extend(config_flags(value, f"{path}."))
        else:
            flags.append(Flag(f"--{path}", _metavar(hints.get(f.name)), value, _docstring(cls, f.name)))
    return flags


def dataparser_flags() -> dict[str, list[Flag]]:
    """Each dataparser subcommand's flags (no prefix), ``auto`` first."""
    configs = {"auto": AutoDataParserConfig(), **{n: s.config for n, s in discover_dataparsers().items()}}
    return {name: config_flags(config) for name, config in configs.items()}


def box_text(stderr: str) -> tuple[str, list[str]]:
    """(title, sections) of a tyro error box printed to ``stderr``, drawn with box characters or (no UTF-8 terminal)
    with ASCII; sections are the box's parts between its rules, each as one line of text."""
    lines = []
    for raw in stderr.splitlines():
        line = raw.strip().strip(BOX_SIDES).strip()
        if line:
            lines.append(line)
    if not lines:
        return "", []
    title = lines[0].strip(BOX_RULES + " ")
    sections: list[str] = []
    current: list[str] = []
    for line in lines[1:]:
        if set(line) <= set(BOX_RULES + " "):
            sections.append(" ".join(current))
            current = []
        else:
            current.append(line)
    sections.append(" ".join(current))
    return title, [s for s in sections if s]


def one_line_error(stderr: str, valid_flags: list[str], subcommands: list[str], prog: str) -> str:
    """tyro's error box as one line: an unknown flag or word with the closest valid names, else its first section."""
    title, sections = box_text(stderr)
    first = sections[0] if sections else (title or "invalid command line")
    unknown = re.match(r"Unrecognized (?:or misplaced )?options:\s*(.*)", first)
    if unknown:
        words = [w.strip(",") for w in re.split(r"[,\s]+", unknown.group(1)) if w.strip(",")]
        words = [w for w in words if not w.startswith("(") and w not in ("applied", "to") and "/" not in w]
        bad = next((w for w in words if w.startswith("-")), words[0] if words else "")
        name = bad.split("=", 1)[0]
        hint = did_you_mean(name, valid_flags if name.startswith("-") else subcommands)
        return f"unrecognized option {name}{hint} (see {prog} --help)"
    return f"{first} (see {prog} --help)"


@contextlib.contextmanager
def tyro_errors_as_one_line(valid_flags: list[str], subcommands: list[str], prog: str):
    """Run a tyro parse; its error box (stderr, SystemExit 2) becomes a :class:`UserError` of one line. Help text and
    a successful parse pass through untouched (anything else it printed to stderr is printed after it)."""
    captured = io.StringIO()
    try:
        with contextlib.redirect_stderr(captured):
            yield
    except SystemExit as exc:
        if exc.code not in (0, None):
            raise UserError(one_line_error(captured.getvalue(), valid_flags, subcommands, prog)) from None
        sys.stderr.write(captured.getvalue())
        raise
    sys.stderr.write(captured.getvalue())


def _format_default(value: Any) -> str:
    if isinstance(value, tuple):
        return " ".join(str(v) for v in value) or "()"
    return str(value)


def _wrap(head: str, names: list[str], width: int) -> list[str]:
    return textwrap.wrap(f"{head}{', '.join(names)}", width=width, subsequent_indent="    ", break_on_hyphens=False)


def short_help(method: str, description: str, config: Any, prog: str = "kc-train") -> str:
    """A method's help on one screen: the flags of SHORT_HELP_FLAGS with their help, one line each; every other flag
    by name, grouped; the learning-rate/schedule flags and the dataparsers named by group."""
    flags = [Flag(SCENE_FLAG, "PATH", None, SHORT_HELP_TEXT[SCENE_FLAG]), *config_flags(config)]
    featured = {f.name: f for f in flags if f.name in SHORT_HELP_FLAGS}
    lines = [f"usage: {prog} {method} --data SCENE [OPTIONS] [DATAPARSER [DATAPARSER OPTIONS]]", "", description, ""]
    for title, names in SHORT_HELP_GROUPS:
        lines.append(f"{title} options:")
        for name in names:
            if name in COMMAND_FLAGS:
                metavar, text = COMMAND_FLAGS[name]
            elif name in featured:
                flag = featured[name]
                metavar = flag.metavar
                text = f"{SHORT_HELP_TEXT.get(flag.name, flag.help)} (default: {_format_default(flag.default)})"
            else:
                continue
            left = f"  {name} {metavar}"
            left = f"{left:<{FLAG_COLUMN}}" if len(left) < FLAG_COLUMN else f"{left} "
            room = SHORT_HELP_WIDTH - len(left)
            lines.append(left + (text if len(text) <= room else text[:room - 3] + "..."))
        lines.append("")
    rest = [f.name for f in flags if f.name not in featured and not f.name[2:].startswith(SHORT_HELP_HIDDEN_PREFIXES)]
    groups: dict[str, list[str]] = {}
    for name in rest:
        head, _, tail = name[2:].rpartition(".")
        groups.setdefault(head, []).append(tail)
    lines.append(f"more options (`{prog} {method} --help-all` explains every flag):")
    for head, tails in groups.items():
        lines.extend(_wrap(f"  {'--' + head + '.' if head else '--'}{{", [], SHORT_HELP_WIDTH)[:0] or
                     _wrap(f"  --{head + '.' if head else ''}{{", tails, SHORT_HELP_WIDTH - 1))
        lines[-1] += "}"
    optimizer = [f for f in flags if f.name.startswith("--optimizers.")]
    if optimizer:
        groups_ = sorted({f.name.split(".")[1] for f in optimizer})
        lines.extend(_wrap(f"  learning rates and schedules ({len(optimizer)} flags): --optimizers.GROUP.{{optimizer.lr, "
                           "scheduler.lr-final, ...} for GROUP in ", groups_, SHORT_HELP_WIDTH))
    lines.append("")
    lines.extend(_wrap(f"dataparser (a subcommand after the options, default auto; `{prog} {method} colmap --help` "
                       "lists its options): ", list(dataparser_flags()), SHORT_HELP_WIDTH))
    return "\n".join(lines)
