"""engine/validation.py and the ranges declared beside the fields (kc_splatfacto/settings.py): every declared rule
refuses a value outside its range with the dotted name, the value and the range, every numeric field of a run's config
declares one, every registered method's defaults are valid, and types are checked against annotations."""

import copy
import dataclasses
import math

import pytest

from kc_splatfacto.data.colmap import ColmapDataParserConfig
from kc_splatfacto.engine.validation import ConfigValueError, validate_config
from kc_splatfacto.registry import discover_methods
from kc_splatfacto.settings import declared_rules
from tests.training_utils import tiny_demo_config


def bad_values(allowed: str):
    """Values outside the range a rule's text states (an independent reading of the text, not of the predicate)."""
    if allowed.startswith("one folder name"):
        return ["/abs/path", "..", "a/b", ""]
    if allowed.startswith("a list"):
        return [(-1,)] if "at least" in allowed else [("squeezenet",)]
    if allowed.startswith("'auto', 'cpu', 'cuda'"):  # a device
        return ["tpu", "CPU", "cuda:", "cuda:-1", "mps", "", 0, None]
    values = [True, "1", float("nan")]
    if "finite" in allowed:
        values += [math.inf, -math.inf]
    if ">= 0" in allowed or "at least 0" in allowed:
        values.append(-1)
    if "> 0" in allowed:
        values += [0, -1e-9]
    if "in [0, 1]" in allowed or "in (0, 1]" in allowed:
        values += [1.5, -0.1]
    if "at least 1" in allowed:
        values += [0, -3]
    if "at least 2" in allowed:
        values.append(1)
    if ".." in allowed:
        low, high = allowed.split("in ")[-1].split(" ")[0].split("..")
        values += [int(low) - 1, int(high) + 1]
    return values


def demo_config():
    return tiny_demo_config("kc-splatfacto", "/tmp/unused")


def colmap_config():
    config = demo_config()
    config.pipeline.datamanager.dataparser = ColmapDataParserConfig()
    return config


CONFIGS = (demo_config, colmap_config)
"""a run's config with each kind of dataparser field (the demo's sizes, COLMAP's split settings)"""


def rule_cases():
    seen = set()
    for make in CONFIGS:
        for name, rule in declared_rules(make()):
            if name in seen:
                continue
            seen.add(name)
            for value in bad_values(rule.allowed):
                yield pytest.param(make, name, value, id=f"{name}={value!r}")


def set_field(config, dotted, value):
    *path, last = dotted.split(".")
    holder = config
    for part in path:
        holder = getattr(holder, part)
    setattr(holder, last, value)


def numeric_fields(config, prefix=""):
    """Dotted names of every int or float field of the config tree (bools are not numbers here)."""
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from numeric_fields(value, f"{prefix}{field.name}.")
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            yield f"{prefix}{field.name}"


@pytest.mark.parametrize("make", CONFIGS)
def test_every_numeric_field_declares_its_range(make):
    config = make()
    declared = {name for name, _ in declared_rules(config)}
    assert set(numeric_fields(config)) <= declared


#: string fields that take any text: names a run folder or a logger shows, an address the viewer binds (checked there)
FREE_TEXT_FIELDS = {"method_name", "logging.wandb_project", "viewer.host"}


def text_fields(config, prefix=""):
    """Dotted names of every str field of the config tree whose annotation is no Literal (a choice tyro checks)."""
    import typing

    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from text_fields(value, f"{prefix}{field.name}.")
        elif isinstance(value, str) and typing.get_origin(hints.get(field.name)) is not typing.Literal:
            yield f"{prefix}{field.name}"


@pytest.mark.parametrize("make", CONFIGS)
def test_every_text_field_that_reaches_a_library_declares_its_range(make):
    """Issue 58: a value a user gives is checked where it enters (``--machine.device tpu`` once reached torch's
    parser inside the trainer, a traceback): every text field is a choice, declares a rule, or takes any text."""
    config = make()
    declared = {name for name, _ in declared_rules(config)}
    assert set(text_fields(config)) - declared <= FREE_TEXT_FIELDS


def test_each_field_rule_is_declared_once_beside_its_field():
    names = [name for name, _ in declared_rules(demo_config())]
    assert len(names) == len(set(names)) and "pipeline.model.frequency.kc_weight" in names


@pytest.mark.parametrize("make, dotted, value", list(rule_cases()))
def test_each_rule_refuses_values_outside_its_range_naming_field_and_value(make, dotted, value):
    config = make()
    set_field(config, dotted, value)
    with pytest.raises(ConfigValueError) as info:
        validate_config(config)
    message = str(info.value)
    assert dotted in message and repr(value) in message and "\n" not in message


@pytest.mark.parametrize("method", sorted(discover_methods()))
def test_every_registered_method_default_is_valid(method):
    validate_config(copy.deepcopy(discover_methods()[method].config))


def test_frequency_loss_needs_a_wavelet_level():
    config = tiny_demo_config("splatfacto", "/tmp/unused")
    config.pipeline.model.frequency.wavelet_levels = 0
    validate_config(config)  # no frequency loss: no level needed
    config.pipeline.model.frequency.kc_weight = 1e-5
    with pytest.raises(ConfigValueError, match=r"pipeline.model.frequency.wavelet_levels = 0 is not allowed: "
                                               r"--pipeline.model.frequency.wavelet-levels must be an integer >= 1 while"):
        validate_config(config)


@pytest.mark.parametrize("dotted, value", [
    ("max_num_iterations", 2.0), ("pipeline.model.use_absgrad", 1), ("pipeline.model.background_color", "grey"),
    ("pipeline.model.ssim_lambda", [0.2]), ("output_dir", 3), ("eval_at_steps", (1.5,)),
    ("pipeline.model.max_num_gaussians", "many"),
])
def test_wrong_types_are_refused(dotted, value):
    config = tiny_demo_config("splatfacto", "/tmp/unused")
    set_field(config, dotted, value)
    with pytest.raises(ConfigValueError, match=f"{dotted} = .* has the wrong type"):
        validate_config(config)


@pytest.mark.parametrize("installed", [False, True], ids=["as-imported", "after-a-command-line"])
def test_missing_dataparser_is_refused_before_and_after_the_cli_installs_subcommands(installed, monkeypatch):
    # the command line's annotation is tyro's subcommand union, which carries a hidden (suppressed) None member: the
    # same config must be refused either way, not only when no command line was built earlier in the process
    from kc_splatfacto.engine import datamanager

    monkeypatch.setattr(datamanager, "DataParserUnion", datamanager.DataParserUnion)  # restored after the test
    if installed:
        datamanager.install_dataparser_subcommands()
        assert "Suppress" in repr(datamanager.DataParserUnion)  # the case this test is about
    config = tiny_demo_config("splatfacto", "/tmp/unused")
    config.pipeline.datamanager.dataparser = None
    with pytest.raises(ConfigValueError, match="pipeline.datamanager.dataparser = None has the wrong type"):
        validate_config(config)
