"""Entry-point and environment-variable discovery of methods."""

import sys

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
