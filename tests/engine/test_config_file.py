"""engine/config_file.py: a TrainerConfig through save_config / read_config_file equal field by field (types
included, against the config written and PyYAML's own unsafe loader), hand edits refused naming the file, the line or
the dotted field, only the project's (and registered plugins') config classes built, the caller's class enforced.

Tested elsewhere and not repeated here: code-running tags in place of a value (os.system, subprocess.Popen,
Path.touch, !!python/name) and garbage YAML (tests/engine/test_run_guard.py), class names of earlier versions and the
committed config files (same), a missing file and a plain mapping (tests/engine/test_trainer.py)."""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import sys
import textwrap
from pathlib import Path

import pytest
import yaml

from kc_splatfacto.engine import config_file
from kc_splatfacto.engine.config_file import read_config_file, save_config
from kc_splatfacto.engine.optimizers import OptimizersConfig
from kc_splatfacto.engine.pipeline import PipelineConfig
from kc_splatfacto.engine.trainer import TrainerConfig
from kc_splatfacto.errors import ConfigFileError
from kc_splatfacto.registry import MethodSpecification, discover_methods
from tests.training_utils import tiny_demo_config

METHODS = sorted(discover_methods())


def assert_same_fields(ours, expected, dotted: str = "config") -> None:
    """Every field of two config trees equal, with the same type (1 is not 1.0, a tuple is not a list)."""
    assert type(ours) is type(expected), f"{dotted}: {type(ours).__name__} vs {type(expected).__name__}"
    if dataclasses.is_dataclass(expected):
        for field in dataclasses.fields(expected):
            assert_same_fields(getattr(ours, field.name), getattr(expected, field.name), f"{dotted}.{field.name}")
    elif isinstance(expected, (tuple, list)):
        assert len(ours) == len(expected), dotted
        for i, (a, b) in enumerate(zip(ours, expected)):
            assert_same_fields(a, b, f"{dotted}[{i}]")
    elif isinstance(expected, float) and math.isnan(expected):
        assert math.isnan(ours), dotted
    else:
        assert ours == expected, f"{dotted}: {ours!r} vs {expected!r}"


@pytest.fixture
def saved(tmp_path) -> tuple[TrainerConfig, Path]:
    config = tiny_demo_config("kc-splatfacto", tmp_path / "runs", iterations=60)
    path = tmp_path / "config.yml"
    save_config(config, path)
    return config, path


def edit(path: Path, pattern: str, replacement: str) -> int:
    """Replace the one line matching ``pattern`` (a regex on the line, indentation kept); its line number."""
    lines = path.read_text().splitlines()
    hits = [i for i, line in enumerate(lines) if re.fullmatch(r"\s*" + pattern, line)]
    assert len(hits) == 1, (pattern, hits)
    indent = re.match(r"\s*", lines[hits[0]]).group(0)
    lines[hits[0]] = indent + replacement
    path.write_text("\n".join(lines) + "\n")
    return hits[0] + 1


def insert_after(path: Path, pattern: str, new_line: str) -> int:
    """Insert ``new_line`` (same indentation) after the one line matching ``pattern``; the new line's number."""
    lines = path.read_text().splitlines()
    hits = [i for i, line in enumerate(lines) if re.fullmatch(r"\s*" + pattern, line)]
    assert len(hits) == 1, (pattern, hits)
    lines.insert(hits[0] + 1, re.match(r"\s*", lines[hits[0]]).group(0) + new_line)
    path.write_text("\n".join(lines) + "\n")
    return hits[0] + 2


# ------------------------------------------------------------------------------------------------ round trip


@pytest.mark.parametrize("method", METHODS)
def test_every_method_config_round_trips_field_by_field(method, tmp_path):
    config = copy.deepcopy(discover_methods()[method].config)
    path = tmp_path / "config.yml"
    save_config(config, path)
    loaded = read_config_file(path, TrainerConfig)
    assert_same_fields(loaded, config)
    assert_same_fields(loaded, yaml.unsafe_load(path.read_text()))  # PyYAML's own reading of the dump


def test_values_yaml_could_misread_round_trip(tmp_path):
    """Strings YAML 1.1 reads as other types unless quoted, paths with spaces and non-ASCII, tuples, small and
    integral floats, big ints: each comes back with its type."""
    config = tiny_demo_config("kc-splatfacto-fine", tmp_path / "out dir/ünï cödé", iterations=123456789)
    config.experiment_name = "yes"
    config.timestamp = "2024-01-02"
    config.method_name = "kc-splatfacto-fine"
    config.eval_at_steps = (0, 3, 1000)
    config.final_lpips_nets = ("alex", "vgg")
    config.load_dir = Path("relative/run: #1")
    config.machine.seed = 2**32 - 1
    config.pipeline.model.ssim_lambda = 0.0
    config.pipeline.model.steps_scale = 1e-7
    config.pipeline.model.random_scale = 10.0
    config.pipeline.datamanager.dataparser.data = Path("null")
    path = tmp_path / "config.yml"
    save_config(config, path)
    assert_same_fields(read_config_file(path, TrainerConfig), config)


# ------------------------------------------------------------------------------------------------ hand edits


@pytest.mark.parametrize("line, edited, dotted, value", [
    (r"max_num_iterations: 60", "max_num_iterations: sixty", "max_num_iterations", "'sixty'"),
    (r"max_num_iterations: 60", "max_num_iterations: 60.0", "max_num_iterations", "60.0"),
    (r"seed: 42", "seed: 4.2", "machine.seed", "4.2"),
    (r"use_absgrad: true", "use_absgrad: 1", "pipeline.model.use_absgrad", "1"),
    (r"ssim_lambda: 0\.2", "ssim_lambda: [0.2]", "pipeline.model.ssim_lambda", "[0.2]"),
    (r"ssim_lambda: 0\.2", "ssim_lambda: 2.0", "pipeline.model.ssim_lambda", "2.0"),
    (r"lr: 0\.00016", "lr: fast", "optimizers.means.optimizer.lr", "'fast'"),
    (r"lr: 0\.00016", "lr: -1.0", "optimizers.means.optimizer.lr", "-1.0"),
])
def test_a_wrong_type_or_range_is_refused_naming_the_file_and_the_dotted_field(saved, line, edited, dotted, value):
    _, path = saved
    edit(path, line, edited)
    with pytest.raises(ConfigFileError) as raised:
        read_config_file(path, TrainerConfig)
    message = str(raised.value)
    assert message.startswith(f"{path}: {dotted} = {value} "), message
    assert message.endswith("fix that value in the file"), message


@pytest.mark.parametrize("after, key, owner, hint", [
    (r"max_num_iterations: 60", "max_num_iteration: 5", "TrainerConfig", "max_num_iterations"),
    (r"ssim_lambda: 0\.2", "ssim_lamda: 0.3", "SplatfactoModelConfig", "ssim_lambda"),
    (r"seed: 42", "colour: red", "MachineConfig", None),
])
def test_an_unknown_key_is_refused_naming_its_line_class_and_the_field_meant(saved, after, key, owner, hint):
    _, path = saved
    number = insert_after(path, after, key)
    name = key.split(":")[0]
    with pytest.raises(ConfigFileError) as raised:
        read_config_file(path, TrainerConfig)
    message = str(raised.value)
    assert message.startswith(f"{path}:{number}: {owner} has no field '{name}'"), message
    assert (f"(did you mean '{hint}'?)" in message) == (hint is not None), message
    assert "fix or remove that line" in message


# ------------------------------------------------------------------------------------------------ allowed classes


@pytest.fixture
def outside_module(tmp_path, monkeypatch):
    """A module outside the project with a config-like dataclass; importing it leaves a marker file."""
    marker = tmp_path / "imported"
    (tmp_path / "kc_outside_mod.py").write_text(textwrap.dedent(f"""
        from dataclasses import dataclass
        from pathlib import Path
        Path({str(marker)!r}).touch()

        @dataclass
        class MachineConfig:
            seed: int = 0
            device: str = "cpu"
    """))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "kc_outside_mod", marker
    sys.modules.pop("kc_outside_mod", None)


def test_a_class_outside_the_project_is_refused_without_importing_its_module(saved, outside_module):
    _, path = saved
    module, marker = outside_module
    number = edit(path, r"machine: !!python/object:\S+", f"machine: !!python/object:{module}.MachineConfig")
    with pytest.raises(ConfigFileError, match=rf"^{path}:{number}: '!!python/object:{module}.MachineConfig' is not a "
                                              "kc-splatfacto config class; refusing to import it"):
        read_config_file(path, TrainerConfig)
    assert not marker.exists() and module not in sys.modules


def test_a_registered_plugins_config_class_is_allowed(tmp_path, outside_module, monkeypatch):
    """The same outside class loads once a method registered through the entry points uses it."""
    module, _ = outside_module
    plugin = __import__(module)  # what loading the plugin's entry point does
    spec = MethodSpecification(config=plugin.MachineConfig(), description="a plugin")
    monkeypatch.setattr(config_file, "discover_methods", lambda: {"plugin-method": spec})
    path = tmp_path / "plugin.yml"
    path.write_text(f"!!python/object:{module}.MachineConfig\nseed: 7\ndevice: cpu\n")
    assert read_config_file(path, plugin.MachineConfig) == plugin.MachineConfig(seed=7)


@pytest.mark.parametrize("tag, refusal", [
    ("!!python/object:kc_splatfacto.engine.trainer.Trainer", "kc_splatfacto.engine.trainer.Trainer is not a config "
                                                             "dataclass; refusing to build it"),
    ("!!python/object:kc_splatfacto.atomic.atomic_write", "is not a config dataclass"),
    ("!!python/object:kc_splatfacto.engine.base_config.NoSuchConfig", "config class kc_splatfacto.engine.base_config."
                                                                      "NoSuchConfig does not exist"),
    ("!!python/object/new:kc_splatfacto.engine.base_config.MachineConfig", "is not allowed in a kc-splatfacto config"),
    ("!!python/module:kc_splatfacto.engine.base_config", "is not allowed in a kc-splatfacto config"),
    ("!include", "tag '!include' is not allowed"),
])
def test_a_tag_other_than_a_config_dataclass_is_refused_naming_its_line(saved, tag, refusal):
    _, path = saved
    number = edit(path, r"machine: !!python/object:\S+", f"machine: {tag}")
    with pytest.raises(ConfigFileError, match=rf"^{path}:{number}: .*{re.escape(refusal)}"):
        read_config_file(path, TrainerConfig)


def test_a_path_must_be_a_list_of_strings(saved):
    _, path = saved
    text = path.read_text()
    assert "\noutput_dir: !!python/object/apply:pathlib.PosixPath\n- /\n" in text
    path.write_text(text.replace("\noutput_dir: !!python/object/apply:pathlib.PosixPath\n- /\n",
                                 "\noutput_dir: !!python/object/apply:pathlib.PosixPath\n- 1\n- /\n"))
    with pytest.raises(ConfigFileError, match=r"a path must be a list of strings, got \[1, '/', "):
        read_config_file(path, TrainerConfig)


# ------------------------------------------------------------------------------------------------ the caller's class


def test_the_file_must_hold_the_callers_class(saved, tmp_path):
    config, trainer_file = saved
    pipeline_file = tmp_path / "pipeline.yml"
    save_config(config.pipeline, pipeline_file)
    with pytest.raises(ConfigFileError, match=rf"{pipeline_file} does not hold a kc-splatfacto TrainerConfig "
                                              r"\(found PipelineConfig\): pass the config.yml of a run folder"):
        read_config_file(pipeline_file, TrainerConfig)
    assert_same_fields(read_config_file(pipeline_file, PipelineConfig), config.pipeline)  # the reader has no class
    with pytest.raises(ConfigFileError, match=r"does not hold a kc-splatfacto OptimizersConfig \(found TrainerConfig\)"):
        read_config_file(trainer_file, OptimizersConfig)
    listing = tmp_path / "list.yml"
    listing.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigFileError, match=r"does not hold a kc-splatfacto TrainerConfig \(found list\)"):
        read_config_file(listing, TrainerConfig)


def test_a_file_that_is_not_text_is_named(tmp_path):
    path = tmp_path / "config.yml"
    path.write_bytes(b"method_name: \xff\xfe\n")
    with pytest.raises(ConfigFileError, match=f"config file {path} cannot be read"):
        read_config_file(path, TrainerConfig)
