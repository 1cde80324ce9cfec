"""A config field's allowed range, declared beside the field: ``refine_every: int = setting(100, integer(1))``.

Every config dataclass of the project (model, losses, dataparsers, engine) declares its numeric and name fields with
:func:`setting`, which keeps the rule in the field's metadata; :func:`range_violations` walks a config tree and yields
each value outside its rule, with its dotted name. A rule between fields (a wavelet level is needed while a frequency
weight is non-zero) is the config class's ``field_conflict()`` method, asked after its fields: it returns the field at
fault and what it must be, or None.

Who checks, and when: the engine checks a whole ``TrainerConfig`` once per run (types from the annotations, then these
ranges: :func:`kc_splatfacto.engine.validation.validate_config`); a config used on its own (``FrequencyLossConfig``
building its loss) checks itself with :func:`check_settings`. This module is a leaf: any layer may use it.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any, Literal

RULE_KEY = "kc_splatfacto.rule"
"""the key of a field's rule in its ``dataclasses.field`` metadata"""
SEED_MAX = 2**32 - 1
"""numpy's ``np.random.seed`` takes 0 .. 2**32 - 1: the range of every seed field"""


@dataclass(frozen=True)
class Rule:
    """A predicate over one value and the text that states it (``"an integer >= 1"``)."""

    check: Callable[[Any], bool]
    allowed: str


def setting(default: Any = dataclasses.MISSING, rule: Rule | None = None, *,
            default_factory: Any = dataclasses.MISSING) -> Any:
    """A dataclass field with ``rule`` as its allowed range (the field's docstring stays under it, as tyro reads
    it)."""
    metadata = {RULE_KEY: rule} if rule is not None else {}
    return dataclasses.field(default=default, default_factory=default_factory, metadata=metadata)


def rule_of(field: dataclasses.Field) -> Rule | None:
    """The rule :func:`setting` declared for ``field``, or None."""
    return field.metadata.get(RULE_KEY)


# ------------------------------------------------------------------------------------------------ rules


def is_int(value: Any) -> bool:
    """An int, not a bool."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_real(value: Any) -> bool:
    """An int or float, not a bool."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def integer(low: int | None = None, high: int | None = None, optional: bool = False) -> Rule:
    """An integer in [low, high] (None also accepted when ``optional``)."""
    text = f"at least {low} (an integer)" if high is None else f"an integer in {low}..{high}"
    if optional:
        text += " (or None)"

    def check(value: Any) -> bool:
        if value is None:
            return optional
        return is_int(value) and (low is None or value >= low) and (high is None or value <= high)

    return Rule(check, text)


def real(low: float | None = None, high: float | None = None, *, low_open: bool = False,
         high_open: bool = False) -> Rule:
    """A finite number in the interval given (open ends where said)."""
    if high is None:
        text = f"a finite number {'>' if low_open else '>='} {low:g}"
    else:
        text = f"a finite number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"

    def check(value: Any) -> bool:
        if not is_real(value) or not math.isfinite(value):
            return False
        if low is not None and (value <= low if low_open else value < low):
            return False
        return not (high is not None and (value >= high if high_open else value > high))

    return Rule(check, text)


def path_component() -> Rule:
    """A run-folder component: one plain folder name, so the run stays inside ``--output-dir``."""

    def check(value: Any) -> bool:
        if value is None:
            return True
        text = str(value)
        return bool(text) and text not in (".", "..") and "/" not in text and "\\" not in text and "\0" not in text

    return Rule(check, "one folder name (no '/', not '..', not absolute) so the run stays inside --output-dir")


def each(rule: Rule) -> Rule:
    """A list or tuple whose items each follow ``rule``."""
    return Rule(lambda value: all(rule.check(v) for v in value), f"a list whose items are each {rule.allowed}")


def drawn_from(*choices: Any) -> Rule:
    """A list or tuple of items among ``choices``."""
    return Rule(lambda value: all(v in choices for v in value), f"a list drawn from {', '.join(map(str, choices))}")


# ------------------------------------------------------------------------------------------------ checking


@dataclass(frozen=True)
class Violation:
    """A value outside its field's rule: the dotted field name, the value, and what it must be."""

    name: str
    value: Any
    allowed: str


def range_violations(config: Any, prefix: str = "") -> Iterator[Violation]:
    """Every value of the config tree ``config`` outside its declared rule, depth first in field order, then each
    config's ``field_conflict()`` ((field, what it must be) or None)."""
    for field in dataclasses.fields(config):
        value = getattr(config, field.name, None)
        name = f"{prefix}{field.name}"
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from range_violations(value, f"{name}.")
            continue
        rule = rule_of(field)
        if rule is not None and not rule.check(value):
            yield Violation(name, value, rule.allowed)
    conflict = getattr(config, "field_conflict", None)
    found = conflict() if callable(conflict) else None
    if found is not None:
        field_name, allowed = found
        yield Violation(f"{prefix}{field_name}", getattr(config, field_name), allowed)


def declared_rules(config: Any, prefix: str = "") -> Iterator[tuple[str, Rule]]:
    """(dotted name, rule) of every field of the tree that declares one."""
    for field in dataclasses.fields(config):
        value = getattr(config, field.name, None)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from declared_rules(value, f"{prefix}{field.name}.")
        elif rule_of(field) is not None:
            yield f"{prefix}{field.name}", rule_of(field)  # type: ignore[misc]


def choice_violations(config: Any) -> Iterator[Violation]:
    """Every field of ``config`` (not its sub-configs) annotated ``Literal[...]`` that holds none of the choices."""
    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        annotation = hints.get(field.name)
        if typing.get_origin(annotation) is Literal:
            choices = typing.get_args(annotation)
            value = getattr(config, field.name)
            if value not in choices:
                yield Violation(field.name, value, f"one of {', '.join(map(repr, choices))}")


def check_settings(config: Any, owner: str) -> None:
    """A ValueError naming ``owner`` and the first value of ``config`` outside its choices or its rule: a config used
    on its own (a loss built in a script), outside a run's ``TrainerConfig`` (which the engine validates whole)."""
    for violation in (*choice_violations(config), *range_violations(config)):
        raise ValueError(f"{owner}: {violation.name} = {violation.value!r} is not allowed: it must be "
                         f"{violation.allowed}")


__all__ = ["SEED_MAX", "Rule", "Violation", "check_settings", "choice_violations", "declared_rules", "drawn_from", "each", "integer",
           "is_int", "is_real", "path_component", "range_violations", "real", "rule_of", "setting"]
