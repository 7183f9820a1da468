"""The layers import one way (kernels <- calibration <- dic) and no modules import each other in a circle.

The import graph is read from the source with ``ast`` (nothing is imported): every ``import`` and
``from ... import`` statement counts, at module level or inside a function, because an import
moved into a function to dodge a circle is still a circle in the design.
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("kernels", "calibration", "dic")
#: Which packages each layer may import (besides itself).
ALLOWED = {"kernels": set(), "calibration": {"kernels"}, "dic": {"kernels", "calibration"}}
def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))}


def _imports(name: str, path: Path, modules) -> list[tuple[str, str | None]]:
    """(imported project module, enclosing top-level function or None) for each import in a module."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []

    def resolve(target: str) -> str | None:
        # the longest project module that the dotted name starts with (a name imported from a module
        # is not a module itself)
        parts = target.split(".")
        for k in range(len(parts), 0, -1):
            candidate = ".".join(parts[:k])
            if candidate in modules:
                return candidate
        return None

    def visit(node, function):
        for child in ast.iter_child_nodes(node):
            inner = function
            if function is None and isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                inner = child.name
            if isinstance(child, ast.Import):
                targets = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")
                    base = base[:len(base) - (child.level - 1)]
                    module = ".".join(base + ([child.module] if child.module else []))
                else:
                    module = child.module or ""
                targets = [f"{module}.{a.name}" for a in child.names]
            else:
                visit(child, inner)
                continue
            for target in targets:
                resolved = resolve(target)
                if resolved is not None and resolved != name and (resolved, function) not in found:
                    found.append((resolved, function))

    visit(tree, None)
    return found


def _graph():
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = [0]

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                strong(w)
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
                out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            strong(v)
    return out


def test_the_graph_sees_imports_inside_functions(tmp_path):
    module = tmp_path / "a.py"
    module.write_text("from .b import thing\n\ndef late():\n    from . import c\n    import pkg.d.e\n")
    modules = {"pkg": None, "pkg.a": module, "pkg.b": None, "pkg.c": None, "pkg.d": None}
    assert _imports("pkg.a", module, modules) == [("pkg.b", None), ("pkg.c", "late"), ("pkg.d", "late")]
    assert _cycles({"x": {"y"}, "y": {"z"}, "z": {"x"}, "w": {"x"}}) == [["x", "y", "z"]]


def test_layers_import_one_way():
    wrong = []
    for name, imports in _graph().items():
        layer = name.split(".")[0]
        for imported, function in imports:
            other = imported.split(".")[0]
            if other != layer and other not in ALLOWED[layer]:
                where = f" (in {function})" if function else ""
                wrong.append(f"{name} imports {imported}{where}")
    assert not wrong, "imports against the layers kernels <- calibration <- dic:\n" + "\n".join(wrong)


def test_no_import_cycles():
    edges = {}
    for name, imports in _graph().items():
        edges[name] = {imported for imported, function in imports}
    cycles = _cycles(edges)
    assert not cycles, "modules importing each other in a circle:\n" + "\n".join(" <-> ".join(c) for c in cycles)
