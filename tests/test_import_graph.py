"""The product's import graph has no cycle: every module of synth, agv_protocol, service, edge_client and agv_fe,
with every import it makes (at the top or inside a function; only imports under ``if TYPE_CHECKING:`` are left out,
they do not run), and importing a module counting as importing the packages above it."""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("synth", "agv_protocol", "service", "edge_client", "agv_fe")


def modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _known(name: str, known: dict[str, Path]) -> str | None:
    """The longest module of ours that ``name`` (a module, or an attribute of one) names."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        candidate = ".".join(parts[:i])
        if candidate in known:
            return candidate
    return None


class _Imports(ast.NodeVisitor):
    def __init__(self, module: str, known: dict[str, Path]) -> None:
        self.module, self.known, self.found = module, known, set[str]()

    def visit_If(self, node: ast.If) -> None:
        test = node.test
        if (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
            isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
        ):
            for child in node.orelse:
                self.visit(child)
            return
        self.generic_visit(node)

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self._add(alias.name)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        assert node.level == 0, f"{self.module}: relative import"
        for alias in node.names:
            self._add(f"{node.module}.{alias.name}")

    def _add(self, name: str) -> None:
        target = _known(name, self.known)
        if target is None or target == self.module:
            return
        parts = target.split(".")
        for i in range(1, len(parts) + 1):  # the packages above it run too
            above = ".".join(parts[:i])
            if above in self.known and not self.module.startswith(above + ".") and above != self.module:
                self.found.add(above)


def import_graph() -> dict[str, set[str]]:
    known = modules()
    graph: dict[str, set[str]] = defaultdict(set)
    for module, path in known.items():
        visitor = _Imports(module, known)
        visitor.visit(ast.parse(path.read_text()))
        graph[module] |= visitor.found
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in list(graph):
        if v not in index:
            visit(v)
    return found


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_module_of_the_product_imports_itself_round_a_cycle():
    graph = import_graph()
    assert len(graph) > 100  # every module was read
    assert cycles(graph) == []


def test_the_math_and_the_protocol_import_nothing_else_and_the_vehicle_side_nothing_of_the_service():
    """Issue 27 item 5: the wire protocol and the Zenoh session configuration live in agv_protocol, which both
    sides import and which imports neither; edge_client imports nothing from service."""
    graph = import_graph()
    assert {"agv_protocol.wire", "agv_protocol.zenoh_session"} <= set(graph)
    for module, imports in graph.items():
        if module.startswith("synth"):
            assert all(i.startswith("synth") for i in imports), (module, imports)
        if module.startswith("agv_protocol"):
            assert all(i.startswith("agv_protocol") for i in imports), (module, imports)
        if module.startswith("edge_client"):
            assert not any(i == "service" or i.startswith("service.") for i in imports), (module, imports)
    assert "agv_protocol.wire" in graph["edge_client.publisher"]
    assert "agv_protocol.zenoh_session" in graph["edge_client.transport"]


def _importers(graph: dict[str, set[str]], target: str) -> set[str]:
    """The modules outside ``target`` (a module or a package) that import it."""
    return {m for m, imports in graph.items() if target in imports and m != target and not m.startswith(target + ".")}


def test_the_service_is_wired_one_way():
    """full-stack-fastapi-template's wiring: service.main alone builds the app from the API and the running
    service, and only the entry points import it; the routes read service.app (through api.deps), and nothing
    below the API (the fleet, the profile policy, storage, transport) imports the API or service.app back."""
    graph = import_graph()
    assert _importers(graph, "service.main") == {"agv_fe.commands.serve"}
    assert _importers(graph, "service.api") == {"service.main"}
    assert _importers(graph, "service.app") <= {"service.main"} | {m for m in graph if m.startswith("service.api.")}
    assert "service.app" in graph["service.api.deps"]
