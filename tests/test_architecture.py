"""The shape of the package that docs/architecture.md promises: no import circle between bcmocap's modules, no
module importing another module's private names, and no function longer than a screenful or two.

The layers themselves are `lint-imports`'s (the contracts in pyproject.toml, run by .ci/run)."""

from __future__ import annotations

import ast
from pathlib import Path

import grimp

PACKAGE = Path(__file__).resolve().parent.parent / "bcmocap"
MAX_FUNCTION_LINES = 150


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _sources() -> list[tuple[str, Path, ast.Module]]:
    return [(_module_name(p), p, ast.parse(p.read_text(), str(p))) for p in sorted(PACKAGE.rglob("*.py"))]


def import_circles(graph) -> list[list[str]]:
    """The strongly connected components of more than one module in ``graph`` (Tarjan, iteratively)."""
    index, low, stack, on_stack, circles, counter = {}, {}, [], set(), [], 0
    for root in sorted(graph.modules):
        if root in index:
            continue
        work = [(root, iter(sorted(graph.find_modules_directly_imported_by(root))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in graph.modules:
                    continue
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.find_modules_directly_imported_by(child)))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    circles.append(sorted(component))
    return circles


def test_the_circle_finder_finds_a_circle():
    class Graph:  # a -> b -> c -> a, and d -> a
        edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
        modules = set(edges)

        def find_modules_directly_imported_by(self, m):
            return self.edges[m]

    assert import_circles(Graph()) == [["a", "b", "c"]]


def test_no_import_circle_between_modules():
    graph = grimp.build_graph("bcmocap")
    assert import_circles(graph) == []


def test_no_private_import_across_modules():
    """``from .x import _name`` reaches into another module's implementation: what two modules share is public
    in the lower one (an ``__init__`` importing its own package's private module is not a name)."""
    found = []
    for module, path, tree in _sources():
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                found += [f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {node.module} {alias.name}"
                          for alias in node.names if alias.name.startswith("_") and not alias.name.startswith("__")]
            elif isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
                base = node.value
                if isinstance(base, ast.Name) and base.id in _imported_modules(tree):
                    found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {base.id}.{node.attr}")
    assert found == []


def _imported_modules(tree: ast.Module) -> set[str]:
    """Local names bound to bcmocap modules (``from . import x``, ``from .. import x``, ``import bcmocap.x as y``)."""
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level and node.module is None:
            names |= {a.asname or a.name for a in node.names}
        elif isinstance(node, ast.Import):
            names |= {a.asname for a in node.names if a.name.startswith("bcmocap") and a.asname}
    return names


def test_no_function_over_the_limit():
    limit = MAX_FUNCTION_LINES
    long = [f"{path.relative_to(PACKAGE.parent)}:{node.lineno} {node.name} ({node.end_lineno - node.lineno + 1} lines)"
            for _, path, tree in _sources() for node in ast.walk(tree)
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.end_lineno - node.lineno + 1 > limit]
    assert long == []
