"""Every user-facing config value checked once, when the config is built: one table of rules, one pass.

A value that reaches numpy, torch or a schedule unchecked fails there with a traceback, or worse trains with a
meaningless setting (``refine_every 0``, an SSIM lambda of 2). :func:`validate_config` walks a ``TrainerConfig``:
first every field against its annotation (an ``int`` field holds an int, not a bool or a string: what a hand-edited
``config.yml`` can hold), then the :data:`RULES` table of ranges. The first violation is a :class:`ConfigValueError`
naming the dotted field, the value and the allowed range, in one line.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib
import types
import typing
from collections.abc import Callable
from typing import Any, Literal, Union

import tyro

from kc_splatfacto.errors import UserError

SEED_MAX = 2**32 - 1
"""numpy's ``np.random.seed`` takes 0 .. 2**32 - 1"""
SH_MAX_DEGREE = 3
"""the renderers' spherical harmonics go up to degree 3 (render/sh.py)"""
LPIPS_NETS = ("alex", "vgg")
"""the LPIPS backbones kc_splatfacto.lpips ships weights for"""
FREQUENCY_WEIGHTS = ("wavelet_weight", "kc_weight", "cbc_weight")


class ConfigValueError(UserError, ValueError):
    """A config field holding a value of the wrong type or outside its range."""


# ------------------------------------------------------------------------------------------------ range predicates


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def integer(low: int | None = None, high: int | None = None, optional: bool = False) -> tuple[Callable, str]:
    """(predicate, text) of an integer in [low, high] (None also accepted when ``optional``)."""
    if high is None:
        text = f"at least {low} (an integer)"
    else:
        text = f"an integer in {low}..{high}"
    if optional:
        text += " (or None)"

    def check(value: Any) -> bool:
        if value is None:
            return optional
        return _is_int(value) and (low is None or value >= low) and (high is None or value <= high)

    return check, text


def real(low: float | None = None, high: float | None = None, *, low_open: bool = False,
         high_open: bool = False) -> tuple[Callable, str]:
    """(predicate, text) of a finite number in the interval given (open ends where said)."""
    if high is None:
        text = f"a finite number {'>' if low_open else '>='} {low:g}"
    else:
        text = f"a finite number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"

    def check(value: Any) -> bool:
        if not _is_real(value) or not math.isfinite(value):
            return False
        if low is not None and (value <= low if low_open else value < low):
            return False
        return not (high is not None and (value >= high if high_open else value > high))

    return check, text


def path_component() -> tuple[Callable, str]:
    """A run-folder component: one plain folder name, so the run stays inside ``--output-dir``."""

    def check(value: Any) -> bool:
        if value is None:
            return True
        text = str(value)
        return bool(text) and text not in (".", "..") and "/" not in text and "\\" not in text and "\0" not in text

    return check, "one folder name (no '/', not '..', not absolute) so the run stays inside --output-dir"


def each(rule: tuple[Callable, str]) -> tuple[Callable, str]:
    check, text = rule
    return (lambda value: all(check(v) for v in value)), f"a list whose items are each {text}"


def one_of(*choices: Any) -> tuple[Callable, str]:
    return (lambda value: all(v in choices for v in value)), f"a list drawn from {', '.join(map(str, choices))}"


#: (dotted field, (predicate, allowed range)); ``*`` stands for any field of that level (optimizer groups)
RULES: tuple[tuple[str, tuple[Callable, str]], ...] = (
    ("max_num_iterations", integer(1)),
    ("steps_per_save", integer(1)),
    ("steps_per_eval_all_images", integer(0)),
    ("eval_at_steps", each(integer(0))),
    ("final_lpips_nets", one_of(*LPIPS_NETS)),
    ("eval_lpips_nets", one_of(*LPIPS_NETS)),
    ("load_step", integer(0, optional=True)),
    ("max_consecutive_bad_steps", integer(1)),
    ("experiment_name", path_component()),
    ("timestamp", path_component()),
    ("machine.seed", integer(0, SEED_MAX)),
    ("logging.steps_per_log", integer(1)),
    ("viewer.port", integer(0, 65535)),
    ("logging.steps_per_gradient_shares", integer(0)),
    ("pipeline.datamanager.dataparser.downscale_factor", integer(1)),
    ("pipeline.datamanager.dataparser.eval_interval", integer(1)),
    ("pipeline.datamanager.dataparser.train_split_fraction", real(0.0, 1.0, low_open=True)),
    ("pipeline.datamanager.dataparser.width", integer(1)),
    ("pipeline.datamanager.dataparser.height", integer(1)),
    ("pipeline.datamanager.dataparser.num_cameras", integer(2)),
    ("pipeline.datamanager.dataparser.num_points", integer(1)),
    ("pipeline.datamanager.dataparser.point_noise", real(0.0)),
    ("pipeline.model.warmup_length", integer(0)),
    ("pipeline.model.refine_every", integer(1)),
    ("pipeline.model.resolution_schedule", integer(1)),
    ("pipeline.model.num_downscales", integer(0, 8)),
    ("pipeline.model.cull_alpha_thresh", real(0.0, 1.0)),
    ("pipeline.model.cull_scale_thresh", real(0.0, low_open=True)),
    ("pipeline.model.reset_alpha_every", integer(1)),
    ("pipeline.model.densify_grad_thresh", real(0.0, low_open=True)),
    ("pipeline.model.densify_size_thresh", real(0.0, low_open=True)),
    ("pipeline.model.n_split_samples", integer(1)),
    ("pipeline.model.max_num_gaussians", integer(1, optional=True)),
    ("pipeline.model.sh_degree_interval", integer(1)),
    ("pipeline.model.cull_screen_size", real(0.0, low_open=True)),
    ("pipeline.model.split_screen_size", real(0.0, low_open=True)),
    ("pipeline.model.stop_screen_size_at", integer(0)),
    ("pipeline.model.num_random", integer(1)),
    ("pipeline.model.random_scale", real(0.0, low_open=True)),
    ("pipeline.model.ssim_lambda", real(0.0, 1.0)),
    ("pipeline.model.stop_split_at", integer(0)),
    ("pipeline.model.sh_degree", integer(0, SH_MAX_DEGREE)),
    ("pipeline.model.sh_views_per_coefficient", real(0.0)),
    ("pipeline.model.max_gauss_ratio", real(1.0)),
    ("pipeline.model.steps_scale", real(0.0, low_open=True)),
    ("pipeline.model.wavelet_weight", real(0.0)),
    ("pipeline.model.kc_weight", real(0.0)),
    ("pipeline.model.cbc_weight", real(0.0)),
    ("pipeline.model.wavelet_levels", integer(0, 16)),
    ("optimizers.*.optimizer.lr", real(0.0, low_open=True)),
    ("optimizers.*.optimizer.eps", real(0.0, low_open=True)),
    ("optimizers.*.optimizer.weight_decay", real(0.0)),
    ("optimizers.*.scheduler.lr_final", real(0.0, low_open=True)),
    ("optimizers.*.scheduler.max_steps", integer(1, optional=True)),
    ("optimizers.*.scheduler.warmup_steps", integer(0)),
    ("optimizers.*.scheduler.lr_pre_warmup", real(0.0)),
)


def _flag(dotted: str) -> str:
    return "--" + dotted.replace("_", "-").removeprefix("pipeline.datamanager.dataparser.")


def _resolve(config: Any, dotted: str) -> list[tuple[str, Any]]:
    """(concrete dotted name, value) for each field ``dotted`` names (``*``: every field of that level); fields a
    config does not have (another dataparser's, a scheduler that is None) are skipped."""
    found = [("", config)]
    for part in dotted.split("."):
        nxt = []
        for name, obj in found:
            if obj is None:
                continue
            if part == "*":
                if dataclasses.is_dataclass(obj):
                    nxt += [(f"{name}{f.name}.", getattr(obj, f.name)) for f in dataclasses.fields(obj)]
                continue
            if hasattr(obj, part):
                nxt.append((f"{name}{part}.", getattr(obj, part)))
        found = nxt
    return [(name.rstrip("."), value) for name, value in found]


def check_ranges(config: Any) -> None:
    """The :data:`RULES` table and the rules between fields; a :class:`ConfigValueError` at the first violation."""
    for dotted, (check, allowed) in RULES:
        for name, value in _resolve(config, dotted):
            if not check(value):
                raise ConfigValueError(f"{name} = {value!r} is not allowed: {_flag(name)} must be {allowed}")
    model = getattr(getattr(config, "pipeline", None), "model", None)
    if model is not None and any(getattr(model, w, 0) for w in FREQUENCY_WEIGHTS) and model.wavelet_levels < 1:
        weights = ", ".join(f"{w} {getattr(model, w)!r}" for w in FREQUENCY_WEIGHTS if getattr(model, w, 0))
        raise ConfigValueError(
            f"pipeline.model.wavelet_levels = {model.wavelet_levels!r} with a non-zero frequency loss ({weights}): "
            "--pipeline.model.wavelet-levels must be an integer >= 1 while a wavelet, KC or CBC weight is non-zero"
        )


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
        return _is_int(value)
    if annotation is float:
        return _is_real(value)
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
                f"{name} = {value!r} has the wrong type ({type(value).__name__}): {_flag(name)} must be "
                f"{_describe(annotation)}"
            )


def validate_config(config: Any) -> None:
    """Types, then ranges, of every field of a ``TrainerConfig`` (see the module docstring)."""
    check_types(config)
    check_ranges(config)


__all__ = ["ConfigValueError", "RULES", "check_ranges", "check_types", "validate_config"]
