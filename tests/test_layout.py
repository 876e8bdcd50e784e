"""The product's layering, read from its sources: the library imports no service package, no
modules import each other in a loop (at module level or inside functions), and the answer
planners are served is composed in one function."""

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"aisdf": ROOT / "shared" / "aisdf", "aisdf_frontend": ROOT / "services" / "frontend",
            "aisdf_mapper": ROOT / "services" / "mapper", "aisdf_query": ROOT / "services" / "query"}


def modules() -> dict[str, Path]:
    out = {}
    for pkg, base in PACKAGES.items():
        for path in base.rglob("*.py"):
            parts = path.relative_to(base).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join((pkg, *parts))] = path
    return out


def import_graph() -> dict[str, set[str]]:
    """Module -> the product's modules it imports anywhere in its file (a ``from x import y``
    of a submodule y counts as importing x.y)."""
    mods = modules()

    def known(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for mod, path in mods.items():
        here = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                deps |= {known(a.name) for a in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = here.split(".")[: len(here.split(".")) - node.level + 1]
                    base = ".".join(up + ([node.module] if node.module else []))
                subs = {f"{base}.{a.name}" for a in node.names} & set(mods)
                deps |= subs or {known(base)}
        graph[mod] = {d for d in deps if d and d != mod}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_graph_sees_imports_at_module_level_and_inside_functions():
    g = import_graph()
    assert "aisdf.query.answer" in g["aisdf.query.engine"]  # module level, relative
    assert "aisdf.mapper.factory" in g["aisdf.bench.query_map"]  # inside a function
    assert "aisdf.query.engine" in g["aisdf_query.main"]  # absolute, from a service
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles():
    assert cycles(import_graph()) == []


def test_the_library_imports_no_service():
    bad = {(m, d) for m, deps in import_graph().items() if m.split(".")[0] == "aisdf"
           for d in deps if d.split(".")[0] != "aisdf"}
    assert not bad, sorted(bad)


def test_the_served_answer_is_composed_in_one_function():
    """``fusion.fuse`` and ``measured_fuse_grad`` (the parts of the served answer) are called
    together only in ``aisdf.query.answer``; the service, the bake and the benchmarks call it."""
    composing = []
    for mod, path in modules().items():
        calls = {n.func.attr if isinstance(n.func, ast.Attribute) else getattr(n.func, "id", None)
                 for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Call)}
        if {"fuse", "measured_fuse_grad"} <= calls or {"fuse", "measured_fuse"} <= calls:
            composing.append(mod)
    assert composing == ["aisdf.query.answer"]
    users = [m for m, deps in import_graph().items() if "aisdf.query.answer" in deps]
    assert {"aisdf.query.engine", "aisdf.query.baker", "aisdf.bench.scaling_walk"} <= set(users)
