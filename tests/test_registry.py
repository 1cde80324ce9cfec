"""Entry-point and environment-variable discovery of methods."""

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
