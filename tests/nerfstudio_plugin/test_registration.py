"""The plugin as nerfstudio sees it, with nerfstudio really installed (``make nerfstudio-env``): ``ns-train --help``
lists every method and the dataparser; each method is nerfstudio's own ``splatfacto`` config (compared field by field
with nerfstudio's ``method_configs``) with the project's frequency-loss settings of the same name; a plugin that fails
to build lists its methods anyway and stops the chosen one with one line."""

from __future__ import annotations

import dataclasses
import importlib.metadata
import os
import subprocess
import sys

import pytest

pytest.importorskip("nerfstudio", reason="nerfstudio is not installed here: run `make test-nerfstudio`")

from kc_splatfacto.losses.frequency import FrequencyLossConfig  # noqa: E402
from kc_splatfacto.nerfstudio_plugin import entry_points  # noqa: E402
from kc_splatfacto.nerfstudio_plugin.configs import PLAIN_SPLATFACTO, method_specifications  # noqa: E402
from kc_splatfacto.nerfstudio_plugin.model import KCSplatfactoModel, KCSplatfactoModelConfig  # noqa: E402
from method_configs import splatfacto_configs  # noqa: E402

NS_TRAIN = [sys.executable, "-m", "nerfstudio.scripts.train"]
ENV = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
PROJECT_METHODS = {spec.config.method_name: spec for spec in vars(splatfacto_configs).values()
                   if type(spec).__name__ == "MethodSpecification"}


def _nerfstudio_name(project_name: str) -> str:
    return PLAIN_SPLATFACTO if project_name == "splatfacto" else project_name


def test_entry_points_register_every_project_method_and_the_dataparser():
    names = {e.name for e in importlib.metadata.entry_points(group=entry_points.METHODS)
             if e.value.startswith(entry_points.__name__)}
    assert names == {_nerfstudio_name(n) for n in PROJECT_METHODS}
    assert set(entry_points.registered_names(entry_points.DATAPARSERS).values()) == {"spars3r"}


def test_ns_train_help_lists_the_methods():
    done = subprocess.run([*NS_TRAIN, "--help"], capture_output=True, text=True, env=ENV, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    for name in PROJECT_METHODS:
        assert _nerfstudio_name(name) in done.stdout
    assert "splatfacto" in done.stdout and "unavailable" not in done.stdout  # nerfstudio's own methods stay


def test_the_dataparser_is_a_subcommand():
    done = subprocess.run([*NS_TRAIN, "kc-splatfacto", "spars3r", "--help"], capture_output=True, text=True, env=ENV,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "--downscale-factor" in done.stdout and "--colmap-path" in done.stdout


def _differences(ours, theirs, path="config") -> list[str]:
    """Paths where two nested configs differ (dataclass fields, dict entries, values)."""
    if dataclasses.is_dataclass(ours) and dataclasses.is_dataclass(theirs):
        if not isinstance(ours, type(theirs)):  # ours may be a subclass of nerfstudio's (same fields, same values)
            return [f"{path}: {type(ours).__name__} is not a {type(theirs).__name__}"]
        found = []
        for field in dataclasses.fields(theirs):
            if field.name == "_target":
                if not issubclass(ours._target, theirs._target):
                    found.append(f"{path}._target")
                continue
            found += _differences(getattr(ours, field.name), getattr(theirs, field.name), f"{path}.{field.name}")
        return found
    if isinstance(ours, dict) and isinstance(theirs, dict):
        if set(ours) != set(theirs):
            return [f"{path}: keys {sorted(ours)} != {sorted(theirs)}"]
        return [d for key in theirs for d in _differences(ours[key], theirs[key], f"{path}[{key!r}]")]
    return [] if ours == theirs else [f"{path}: {ours!r} != {theirs!r}"]


def test_every_method_is_nerfstudios_splatfacto_config_with_the_project_loss_settings():
    from nerfstudio.configs.method_configs import method_configs

    reference = method_configs["splatfacto"]
    specs = method_specifications()
    assert set(specs) == {_nerfstudio_name(n) for n in PROJECT_METHODS}
    for name, project in PROJECT_METHODS.items():
        config = specs[_nerfstudio_name(name)].config
        assert config.method_name == _nerfstudio_name(name)
        model = config.pipeline.model
        assert isinstance(model, KCSplatfactoModelConfig) and model._target is KCSplatfactoModel
        differences = [d for d in _differences(config, reference) if not d.startswith("config.method_name")]
        # nerfstudio's Splatfacto fields all keep nerfstudio's values, except the ones the project's method changes
        changed = {f.name for f in dataclasses.fields(project.config.pipeline.model)
                   if getattr(project.config.pipeline.model, f.name)
                   != getattr(splatfacto_configs.splatfacto.config.pipeline.model, f.name)}
        allowed = {f"config.pipeline.model.{n}" for n in changed}
        assert all(d.split(":")[0] in allowed for d in differences), (name, differences)
        assert model.frequency == project.config.pipeline.model.frequency, name  # kc-train's settings, same values


def test_the_frequency_settings_default_to_the_papers():
    model = KCSplatfactoModelConfig()
    assert model.frequency == FrequencyLossConfig()
    assert not method_specifications()[PLAIN_SPLATFACTO].config.pipeline.model.frequency.active


BROKEN = """
import sys
sys.modules['kc_splatfacto.nerfstudio_plugin.configs'] = None     # `import` of these raises ImportError
sys.modules['kc_splatfacto.nerfstudio_plugin.dataparser'] = None
sys.argv = ['ns-train', *sys.argv[1:]]
from nerfstudio.scripts.train import entrypoint
entrypoint()
"""


def test_a_plugin_that_cannot_be_built_lists_its_methods_and_stops_the_chosen_one_with_one_line(tmp_path):
    listed = subprocess.run([sys.executable, "-c", BROKEN, "--help"], capture_output=True, text=True, env=ENV,
                            timeout=300)
    assert listed.returncode == 0, listed.stderr[-2000:]
    assert "kc-splatfacto" in listed.stdout and "unavailable" in listed.stdout
    other = subprocess.run([sys.executable, "-c", BROKEN, "splatfacto", "--help"], capture_output=True, text=True,
                           env=ENV, timeout=300)
    assert other.returncode == 0, other.stderr[-2000:]  # nerfstudio's own methods are untouched

    chosen = subprocess.run([sys.executable, "-c", BROKEN, "kc-splatfacto", "--data", str(tmp_path)],
                            capture_output=True, text=True, env=ENV, timeout=300, cwd=tmp_path)
    lines = [line for line in chosen.stderr.splitlines() if line.startswith("kc-splatfacto:")]
    assert chosen.returncode == 1 and len(lines) == 1, chosen.stderr[-2000:]
    assert "ns-train kc-splatfacto is unavailable: ModuleNotFoundError: import of kc_splatfacto" in lines[0]
    assert "pip install 'kc-splatfacto[nerfstudio]'" in lines[0]
    assert "Traceback" not in chosen.stderr
    assert not (tmp_path / "outputs").exists()  # stopped before anything was written

    parser = subprocess.run([sys.executable, "-c", BROKEN, "splatfacto", "--data", str(tmp_path), "spars3r"],
                            capture_output=True, text=True, env=ENV, timeout=300, cwd=tmp_path)
    assert parser.returncode == 1 and "the dataparser spars3r is unavailable" in parser.stderr, parser.stderr[-2000:]
