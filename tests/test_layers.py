"""The layering docs/architecture.md claims, checked on the source: imports only go down the stack and the engine's
modules import each other without a circle. Every import statement counts, at module level or inside a function
(a circle closed by an import inside a function is still a circle); only ``if TYPE_CHECKING:`` blocks are left out,
since they never run (type checkers resolve circles among annotations)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "kc_splatfacto"
#: lower index = lower layer; a module may import its own layer and lower ones. The top-level modules are leaves any
#: layer may use: errors (imports nothing of the package), atomic (nothing), backend (errors), lpips (nothing),
#: registry (errors), metrics (lpips). Every top-level module and subpackage must be in one layer.
LAYERS = ["errors", "settings", "atomic", "backend", "lpips", "registry", "metrics", "render", "losses", "data", "model", "plan", "engine",
          "analysis", "study", "viewer", "cli", "nerfstudio_plugin"]


def _is_type_checking_block(node: ast.AST) -> bool:
    if not isinstance(node, ast.If):
        return False
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _import_nodes(tree: ast.AST):
    """Every Import/ImportFrom under ``tree`` (functions, classes, try blocks included), except in TYPE_CHECKING."""
    stack = [tree]
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        stack.extend(child for child in ast.iter_child_nodes(node) if not _is_type_checking_block(child))


def _absolute(node: ast.ImportFrom, module_name: str, is_package: bool, root: str) -> str | None:
    """The absolute module an ImportFrom names (a relative one resolved against ``module_name``)."""
    if node.level == 0:
        return node.module
    base = module_name.split(".")
    base = base if is_package else base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else [])) if base and base[0] == root else None


def module_imports(path: Path, package_dir: Path = PACKAGE) -> set[str]:
    """Modules of the package at ``package_dir`` that the file at ``path`` imports, anywhere in the file."""
    root = package_dir.name
    relative = path.relative_to(package_dir).with_suffix("")
    is_package = relative.name == "__init__"
    module_name = ".".join([root, *(relative.parts[:-1] if is_package else relative.parts)])
    found = set()
    for node in _import_nodes(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            module = _absolute(node, module_name, is_package, root)
            if module and module.split(".")[0] == root:
                found.add(module)
                found.update(f"{module}.{alias.name}" for alias in node.names)
        else:
            found.update(alias.name for alias in node.names if alias.name.split(".")[0] == root)
    return found


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else None


def import_graph(folder: Path, package_dir: Path = PACKAGE) -> dict[str, set[str]]:
    """{module stem: stems of the same folder it imports} for the modules of ``folder`` (a subpackage)."""
    modules = {p.stem: p for p in folder.glob("*.py") if p.stem != "__init__"}
    prefix = ".".join([package_dir.name, *folder.relative_to(package_dir).parts]) + "."
    return {
        name: {m[len(prefix):].split(".")[0] for m in module_imports(path, package_dir) if m.startswith(prefix)}
        & set(modules) - {name}
        for name, path in modules.items()
    }


def find_circle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle of ``graph`` as a list of names (first == last), or None."""
    visiting, done = set(), set()

    def visit(name: str, trail: list[str]) -> list[str] | None:
        if name in visiting:
            return trail[trail.index(name):] + [name]
        if name in done:
            return None
        visiting.add(name)
        for other in sorted(graph[name]):
            circle = visit(other, trail + [name])
            if circle:
                return circle
        visiting.discard(name)
        done.add(name)
        return None

    for name in sorted(graph):
        circle = visit(name, [])
        if circle:
            return circle
    return None


def modules_without_a_layer(package_dir: Path = PACKAGE) -> list[str]:
    """Top-level modules and subpackages (any folder holding Python files) of the package that no layer names."""
    found = [p.stem if p.is_file() else p.name for p in package_dir.iterdir()
             if (p.is_file() and p.suffix == ".py" and p.stem != "__init__") or (p.is_dir() and any(p.rglob("*.py")))]
    return sorted(name for name in found if name not in LAYERS)


def test_every_module_is_in_a_layer():
    """A new top-level module or subpackage must be placed in LAYERS (and docs/architecture.md): one in no layer would
    escape the import check below."""
    assert modules_without_a_layer() == [], f"add these to LAYERS: {modules_without_a_layer()}"


def test_the_layer_check_finds_a_new_module_and_subpackage(tmp_path):
    package = _write_package(tmp_path, {"errors.py": "", "helpers.py": "", "newpkg/__init__.py": "",
                                        "plain_folder/tool.py": "", "render/__init__.py": ""})
    (package / "__pycache__").mkdir()
    (package / "notes").mkdir()
    (package / "notes" / "readme.txt").write_text("no Python here")
    assert modules_without_a_layer(package) == ["helpers", "newpkg", "plain_folder"]


def test_imports_only_go_down_the_layers():
    upward = []
    for path in PACKAGE.rglob("*.py"):
        here = _layer("kc_splatfacto." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts))
        if here is None:
            continue
        for module in module_imports(path):
            there = _layer(module)
            if there is not None and LAYERS.index(there) > LAYERS.index(here):
                upward.append(f"{path.relative_to(PACKAGE)} imports {module}")
    assert not upward, upward


def test_engine_modules_import_each_other_without_a_circle():
    graph = import_graph(PACKAGE / "engine")
    # the checker sees edges, those inside functions included (datamanager's were all inside functions once)
    assert graph["trainer"] >= {"pipeline", "run_guard", "config_file"} and "datamanager" in graph["pipeline"]
    assert {"trainer", "config_file"} <= graph["config"]  # config.yml as a TrainerConfig: above the trainer
    assert find_circle(graph) is None, " -> ".join(find_circle(graph))


@pytest.mark.parametrize("folder", sorted(p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()))
def test_no_subpackage_has_an_import_circle(folder):
    circle = find_circle(import_graph(PACKAGE / folder))
    assert circle is None, f"{folder}: " + " -> ".join(circle)


def _write_package(root: Path, files: dict[str, str]) -> Path:
    package = root / "kc_splatfacto"
    for name, text in {"__init__.py": "", "engine/__init__.py": "", **files}.items():
        (package / name).parent.mkdir(parents=True, exist_ok=True)
        (package / name).write_text(text)
    return package


def test_the_checker_finds_a_circle_closed_inside_a_function(tmp_path):
    """A planted circle: ``a`` imports ``b`` at the top, ``b`` imports ``a`` inside a function (and, separately, a
    relative import inside a method); the checker must report both, and must not count a TYPE_CHECKING import."""
    package = _write_package(tmp_path, {
        "engine/a.py": "from kc_splatfacto.engine import b\n",
        "engine/b.py": "def load():\n    from kc_splatfacto.engine.a import thing\n    return thing\n",
        "engine/c.py": "class C:\n    def m(self):\n        from .d import x\n        return x\n",
        "engine/d.py": "import kc_splatfacto.engine.c\n",
        "engine/e.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from kc_splatfacto.engine.f import F\n",
        "engine/f.py": "from kc_splatfacto.engine.e import thing\n",
    })
    graph = import_graph(package / "engine", package)
    assert graph["b"] == {"a"} and graph["c"] == {"d"} and graph["d"] == {"c"}
    assert graph["e"] == set() and graph["f"] == {"e"}
    assert find_circle({k: graph[k] for k in ("a", "b")}) == ["a", "b", "a"]
    assert find_circle({k: graph[k] for k in ("c", "d")}) == ["c", "d", "c"]
    assert find_circle({k: graph[k] for k in ("e", "f")}) is None


def test_the_checker_finds_an_upward_import_inside_a_function(tmp_path):
    package = _write_package(tmp_path, {"render/__init__.py": "", "render/r.py": (
        "def show():\n    try:\n        from kc_splatfacto.viewer.v import View\n    except ImportError:\n"
        "        return None\n    return View\n")})
    assert "kc_splatfacto.viewer.v" in module_imports(package / "render" / "r.py", package)
