"""The import graph of ``service/`` (every module parsed with ``ast``, nothing imported): the
model's domain packages import downward only (no cycle between them, and no cycle between the
modules of ``service.model`` and ``service.storage``), and the model imports nothing from the
web, application or storage layers. See docs/layout.md for the layers.

The application layer's one ``Context`` makes its modules one cycle today; it is left for the
next step (docs/layout.md), so its modules are not checked for cycles yet.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

SERVICE = Path(__file__).resolve().parents[1] / "service"
MODEL_MAY_NOT_IMPORT = ("service.api", "service.application", "service.storage")
ACYCLIC_LAYERS = ("service.model", "service.storage")


def module_names(root: Path = SERVICE) -> dict[str, Path]:
    """Dotted name -> file, for every module and package of ``service``."""
    out = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _type_checking_only(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    """Under ``if TYPE_CHECKING:`` (not imported at run time)."""
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            return True
    return False


def imports_of(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The ``service`` modules that module ``name`` imports (at module level or in functions;
    ``from pkg import mod`` counts as an import of ``pkg.mod``), resolving relative imports."""
    tree = ast.parse(path.read_text(), str(path))
    parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    is_package = path.name == "__init__.py"
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")[: len(name.split(".")) - node.level + (1 if is_package else 0)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            targets = [f"{module}.{a.name}" if f"{module}.{a.name}" in modules else module for a in node.names]
        else:
            continue
        if _type_checking_only(node, parents):
            continue
        for t in targets:
            while t and t not in modules:  # ``import service.model.x.y`` names the deepest module
                t = t.rpartition(".")[0]
            if t.startswith("service") and t != name:
                out.add(t)
    return out


def import_graph(root: Path = SERVICE) -> dict[str, set[str]]:
    modules = module_names(root)
    return {name: imports_of(name, path, modules) for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a list of nodes (first == last), or None."""
    WHITE, GREY, BLACK = 0, 1, 2
    colour = dict.fromkeys(graph, WHITE)
    stack: list[str] = []

    def visit(u: str) -> list[str] | None:
        colour[u] = GREY
        stack.append(u)
        for v in sorted(graph.get(u, ())):
            if colour.get(v, BLACK) == GREY:
                return stack[stack.index(v):] + [v]
            if colour.get(v) == WHITE:
                found = visit(v)
                if found:
                    return found
        stack.pop()
        colour[u] = BLACK
        return None

    for u in sorted(graph):
        if colour[u] == WHITE:
            found = visit(u)
            if found:
                return found
    return None


def model_package(name: str) -> str | None:
    """``service.model.body.lbs`` -> ``service.model.body``; None outside the model's packages."""
    parts = name.split(".")
    return ".".join(parts[:3]) if len(parts) >= 3 and parts[:2] == ["service", "model"] else None


@pytest.fixture(scope="module")
def graph() -> dict[str, set[str]]:
    return import_graph()


def test_the_graph_sees_the_imports(graph):
    """The parser finds absolute, ``from package import module`` and function-level imports."""
    assert "service.model.geometry.mesh" in graph["service.model.body.poses"]
    assert "service.model.fitting.person_check" in graph["service.model.fitting.checks"]
    assert "service.model.garments.tryon" in graph["service.model.garments.autofit"]  # inside a function


def test_model_packages_import_downward(graph):
    """No cycle between the model's domain packages (body, garments, fitting, ...)."""
    packages: dict[str, set[str]] = {}
    for name, targets in graph.items():
        src = model_package(name)
        if src is None:
            continue
        packages.setdefault(src, set()).update(
            dst for dst in map(model_package, targets) if dst is not None and dst != src)
    assert len(packages) >= 5, packages
    cycle = find_cycle(packages)
    assert cycle is None, " -> ".join(cycle)


@pytest.mark.parametrize("layer", ACYCLIC_LAYERS)
def test_no_module_cycle(graph, layer):
    sub = {n: {t for t in ts if t.startswith(layer + ".")} for n, ts in graph.items() if n.startswith(layer + ".")}
    cycle = find_cycle(sub)
    assert cycle is None, " -> ".join(cycle)


def test_model_imports_no_outer_layer(graph):
    bad = sorted((n, t) for n, ts in graph.items() if n.startswith("service.model") for t in ts
                 if t.startswith(MODEL_MAY_NOT_IMPORT))
    assert not bad, bad


def test_the_checks_can_fail():
    """The cycle finder and the layer check on a small made-up graph."""
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert model_package("service.model.body.lbs") == "service.model.body"
    assert model_package("service.storage.bases") is None
