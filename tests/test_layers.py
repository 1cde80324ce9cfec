"""The layering docs/architecture.md claims, checked on the source: module-level imports only go down the stack and
the engine's modules import each other without a circle."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "kc_splatfacto"
#: lower index = lower layer; a module may import its own layer and lower ones (registry/atomic/metrics: leaves)
LAYERS = ["atomic", "registry", "metrics", "render", "losses", "data", "model", "engine", "analysis", "study", "cli"]


def _module_imports(path: Path) -> set[str]:
    """kc_splatfacto modules imported at module level (not inside functions) by the file at ``path``."""
    found = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("kc_splatfacto"):
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names if alias.name.startswith("kc_splatfacto"))
    return found


def _layer(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in LAYERS else None


def test_module_level_imports_only_go_down_the_layers():
    upward = []
    for path in PACKAGE.rglob("*.py"):
        here = _layer("kc_splatfacto." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts))
        if here is None:
            continue
        for module in _module_imports(path):
            there = _layer(module)
            if there is not None and LAYERS.index(there) > LAYERS.index(here):
                upward.append(f"{path.relative_to(PACKAGE)} imports {module}")
    assert not upward, upward


def test_engine_modules_import_each_other_without_a_circle():
    engine = {p.stem: p for p in (PACKAGE / "engine").glob("*.py") if p.stem != "__init__"}
    graph = {
        name: {m.split(".")[2] for m in _module_imports(path) if m.startswith("kc_splatfacto.engine.")} & set(engine)
        for name, path in engine.items()
    }
    assert graph["trainer"] >= {"pipeline", "config"} and "datamanager" in graph["pipeline"]  # the checker sees edges
    visiting, done = set(), set()

    def visit(name: str, trail: list[str]) -> None:
        assert name not in visiting, "import circle: " + " -> ".join(trail + [name])
        if name in done:
            return
        visiting.add(name)
        for other in graph[name]:
            visit(other, trail + [name])
        visiting.discard(name)
        done.add(name)

    for name in graph:
        visit(name, [])
