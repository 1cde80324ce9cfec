"""Entry-point and environment-variable discovery of methods."""

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest

from kc_splatfacto import registry
from kc_splatfacto.registry import MethodSpecification, RegistryError, discover_methods

dummy_method = MethodSpecification(config={"name": "dummy"}, description="a throwaway method for tests")
not_a_spec = 42


def test_env_var_adds_a_method(monkeypatch):
    monkeypatch.setenv(registry.METHOD_ENV, "dummy-env=tests.test_registry:dummy_method")
    methods = discover_methods()
    assert methods["dummy-env"] is dummy_method


def test_env_var_with_wrong_type_names_the_item(monkeypatch):
    monkeypatch.setenv(registry.METHOD_ENV, "bad=tests.test_registry:not_a_spec")
    with pytest.raises(RegistryError, match="bad=tests.test_registry:not_a_spec"):
        discover_methods()


def test_env_var_with_missing_module_is_a_clear_error(monkeypatch):
    monkeypatch.setenv(registry.METHOD_ENV, "ghost=no_such_module_xyz:spec")
    with pytest.raises(RegistryError, match="no_such_module_xyz"):
        discover_methods()


def test_env_var_malformed(monkeypatch):
    monkeypatch.setenv(registry.METHOD_ENV, "just-a-name")
    with pytest.raises(RegistryError, match="name=module:attribute"):
        discover_methods()


def test_a_method_that_replaces_a_registered_name_is_said_once(monkeypatch):
    """Issue 37: the environment variable's 'splatfacto' replaces the built-in one (the later registration wins) with
    one warning naming both; a name given twice in the variable likewise."""
    import warnings

    monkeypatch.setenv(registry.METHOD_ENV, "splatfacto=tests.test_registry:dummy_method,"
                                            "twice=tests.test_registry:dummy_method,twice=method_configs.splatfacto_configs:kc_splatfacto")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for _ in range(3):  # discovery runs many times in a command: the warning is still said once
            methods = discover_methods()
    assert methods["splatfacto"] is dummy_method and methods["twice"].config.method_name == "kc-splatfacto"
    assert sorted(str(w.message) for w in caught) == [
        f"{registry.METHOD_ENV}'s splatfacto=tests.test_registry:dummy_method replaces the built-in method 'splatfacto' "
        "(method_configs.splatfacto_configs:splatfacto); give it another name to keep both",
        f"{registry.METHOD_ENV}'s twice=method_configs.splatfacto_configs:kc_splatfacto replaces the method 'twice' of "
        f"{registry.METHOD_ENV} (tests.test_registry:dummy_method); give it another name to keep both",
    ]


def test_a_namesake_method_configs_package_is_refused(tmp_path, monkeypatch):
    """Another top-level ``method_configs`` earlier on sys.path (with a ``splatfacto_configs`` of its own) is named,
    not trained under this project's method names."""
    namesake = tmp_path / "method_configs"
    namesake.mkdir()
    (namesake / "__init__.py").write_text("")
    (namesake / "splatfacto_configs.py").write_text(
        "from kc_splatfacto.registry import MethodSpecification\n"
        + "".join(f"{n} = MethodSpecification(config=None, description='namesake')\n" for n in (
            "splatfacto", "kc_splatfacto", "kc_splatfacto_fine", "ablation_l1_wavelet", "ablation_wavelet",
            "ablation_unscaled_wavelet", "ablation_heavy_wavelet", "ablation_scaled_cbc", "kc_splatfacto_corr")))
    for name in [m for m in sys.modules if m == "method_configs" or m.startswith("method_configs.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(RegistryError, match=f"imported from {namesake}.*not kc-splatfacto's"):
        discover_methods()
    for name in [m for m in sys.modules if m == "method_configs" or m.startswith("method_configs.")]:
        del sys.modules[name]  # the namesake goes; monkeypatch puts the project's own modules back


BROKEN_PLUGIN = """
import importlib.metadata as metadata
real = metadata.entry_points

def entry_points(**selection):
    if selection.get("group", "").startswith("kc_splatfacto."):  # one third-party plugin that no longer imports
        return [metadata.EntryPoint("broken", "no_such_plugin_module_xyz:spec", selection["group"])]
    return real(**selection)

metadata.entry_points = entry_points
import kc_splatfacto.engine.config, kc_splatfacto.engine.run_io, kc_splatfacto.engine.trainer  # noqa: E401
import kc_splatfacto.cli.eval, kc_splatfacto.cli.train  # noqa: E401
print("imported")
from kc_splatfacto.registry import RegistryError, discover_dataparsers
try:
    discover_dataparsers()
except RegistryError as exc:
    print("discovery:", exc)
"""


def test_a_broken_plugin_does_not_break_importing_the_engine(tmp_path):
    """Importing the engine and the CLI modules discovers nothing: a broken third-party entry point fails the command
    that lists plugins (naming itself), never ``import kc_splatfacto.engine.trainer``. A fresh interpreter, because
    this one has imported the engine already."""
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run([sys.executable, "-c", BROKEN_PLUGIN], capture_output=True, text=True, env=env, cwd=tmp_path,
                          timeout=600)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "imported"
    # the patched entry points are the ones discovery reads: the same plugin fails discovery, naming itself
    assert lines[1].startswith("discovery: entry point 'broken'") and "no_such_plugin_module_xyz" in lines[1]


def test_experimental_methods_load_through_the_env_var_and_differ_from_their_base_in_the_sh_cap_only(monkeypatch):
    monkeypatch.delenv(registry.METHOD_ENV, raising=False)
    registered = discover_methods()
    assert "splatfacto-sparse-sh" not in registered  # not registered until a study shows it helps
    monkeypatch.setenv(registry.METHOD_ENV, "splatfacto-sparse-sh=method_configs.experiments:splatfacto_sparse_sh,"
                       "kc-splatfacto-sparse-sh=method_configs.experiments:kc_splatfacto_sparse_sh")
    methods = discover_methods()
    for variant, base in (("splatfacto-sparse-sh", "splatfacto"), ("kc-splatfacto-sparse-sh", "kc-splatfacto")):
        model = dataclasses.asdict(methods[variant].config.pipeline.model)
        base_model = dataclasses.asdict(registered[base].config.pipeline.model)
        assert model.pop("sh_views_per_coefficient") == 2.0 and base_model.pop("sh_views_per_coefficient") == 0.0
        assert model == base_model
        assert methods[variant].config.method_name == variant
