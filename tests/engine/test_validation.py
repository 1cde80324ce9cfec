"""engine/validation.py (issue 26): every rule of the table refuses a value outside its range with the dotted name,
the value and the range, and accepts every registered method's defaults; types are checked against annotations."""

import copy
import math

import pytest

from kc_splatfacto.data.colmap import ColmapDataParserConfig
from kc_splatfacto.engine.validation import RULES, ConfigValueError, _resolve, validate_config
from kc_splatfacto.registry import discover_methods
from tests.training_utils import tiny_demo_config


def bad_values(allowed: str):
    """Values outside the range a rule's text states (an independent reading of the text, not of the predicate)."""
    if allowed.startswith("one folder name"):
        return ["/abs/path", "..", "a/b", ""]
    if allowed.startswith("a list"):
        return [(-1,)] if "at least" in allowed else [("squeezenet",)]
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


def config_with(dotted):
    """The tiny demo config, or with a COLMAP dataparser for the fields the demo's has not."""
    config = tiny_demo_config("kc-splatfacto", "/tmp/unused")
    if not _resolve(config, dotted):
        config.pipeline.datamanager.dataparser = ColmapDataParserConfig()
    return config


def rule_cases():
    for dotted, (_, allowed) in RULES:
        for name, _ in _resolve(config_with(dotted), dotted):
            for value in bad_values(allowed):
                yield pytest.param(name, value, id=f"{name}={value!r}")


def set_field(config, dotted, value):
    *path, last = dotted.split(".")
    holder = config
    for part in path:
        holder = getattr(holder, part)
    setattr(holder, last, value)


def test_the_table_covers_every_dataparser_rule():
    assert all(_resolve(config_with(dotted), dotted) for dotted, _ in RULES)


@pytest.mark.parametrize("dotted, value", list(rule_cases()))
def test_each_rule_refuses_values_outside_its_range_naming_field_and_value(dotted, value):
    config = config_with(dotted)
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
    config.pipeline.model.wavelet_levels = 0
    validate_config(config)  # no frequency loss: no level needed
    config.pipeline.model.kc_weight = 1e-5
    with pytest.raises(ConfigValueError, match="pipeline.model.wavelet_levels = 0 with a non-zero frequency loss"):
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
