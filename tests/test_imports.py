"""The import graph of ``service/`` (every module parsed with ``ast``, nothing imported; imports
under ``if TYPE_CHECKING:`` count too, being a cycle of the code if not of the run): no cycle
between any of its modules, the model's domain packages import downward only, the layers import
downward only (api -> application -> model and storage; storage imports no application or
api; the model no api, application or storage), and no module outside ``service/storage/``
imports ``redis``. See docs/architecture.md for the layers.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

SERVICE = Path(__file__).resolve().parents[1] / "service"
MODEL_MAY_NOT_IMPORT = ("service.api", "service.application", "service.storage")
# what each layer may not import (the layers below it are allowed)
MAY_NOT_IMPORT = {
    "service.model": MODEL_MAY_NOT_IMPORT,
    "service.storage": ("service.api", "service.application"),
    "service.application": ("service.api",),
}
ACYCLIC_LAYERS = ("service.model", "service.storage", "service.application", "service.api")
REDIS_LAYER = "service.storage"


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


def imports_of(name: str, path: Path, modules: dict[str, Path], type_checking: bool = True,
               external: bool = False) -> set[str]:
    """The ``service`` modules that module ``name`` imports (at module level or in functions;
    ``from pkg import mod`` counts as an import of ``pkg.mod``), resolving relative imports;
    ``type_checking``: those under ``if TYPE_CHECKING:`` too. ``external``: the top-level names
    of the other packages it imports instead (``redis``, ``numpy``, ...)."""
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
        if not type_checking and _type_checking_only(node, parents):
            continue
        if external:
            if not (isinstance(node, ast.ImportFrom) and node.level):
                out.update(t.split(".")[0] for t in targets if not t.startswith("service"))
            continue
        for t in targets:
            while t and t not in modules:  # ``import service.model.x.y`` names the deepest module
                t = t.rpartition(".")[0]
            if t.startswith("service") and t != name:
                out.add(t)
    return out


def import_graph(root: Path = SERVICE, external: bool = False) -> dict[str, set[str]]:
    modules = module_names(root)
    return {name: imports_of(name, path, modules, external=external) for name, path in modules.items()}


def layer_violations(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(module, import) pairs where a layer imports one above it (:data:`MAY_NOT_IMPORT`)."""
    return sorted((n, t) for n, ts in graph.items() for layer, banned in MAY_NOT_IMPORT.items()
                  if n == layer or n.startswith(layer + ".") for t in ts if t.startswith(banned))


def redis_importers(external: dict[str, set[str]]) -> list[str]:
    """The modules outside ``service.storage`` that import the ``redis`` client."""
    return sorted(n for n, ts in external.items()
                  if "redis" in ts and not (n == REDIS_LAYER or n.startswith(REDIS_LAYER + ".")))


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


def test_no_cycle_in_service(graph):
    """No cycle anywhere in ``service/`` (across the layers and inside each), ``TYPE_CHECKING``
    imports included."""
    cycle = find_cycle(graph)
    assert cycle is None, " -> ".join(cycle)


def test_layers_import_downward(graph):
    assert not layer_violations(graph)


def test_application_services_get_their_collaborators(graph):
    """No use case imports the composition root (``service.application.context``): each is
    handed its collaborators; only the API's dependencies, the app factory and the worker's
    jobs (outside ``service/``) reach the root."""
    root = "service.application.context"
    importers = sorted(n for n, ts in graph.items() if root in ts)
    assert importers and set(importers) <= {"service.api.deps", "service.app"}, importers


def test_redis_is_imported_only_by_storage():
    external = import_graph(external=True)
    assert "redis" in external["service.storage.redis"]  # the check sees the imports
    assert not redis_importers(external)


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
    assert layer_violations({"service.storage.x": {"service.application.y"}, "service.api.a": {"service.model.b"}}) \
        == [("service.storage.x", "service.application.y")]
    assert layer_violations({"service.model.body.x": {"service.storage.y"}}) == [("service.model.body.x", "service.storage.y")]
    assert redis_importers({"service.application.poses": {"redis", "numpy"}, "service.storage.queue": {"redis"}}) \
        == ["service.application.poses"]
