"""The package's import structure (issue: no cycles, no private names across modules, layers in
the book's order): read from the source with ``ast``, every ``import`` counted, including those
inside functions (a lazy import hides a cycle, it does not remove it)."""

from __future__ import annotations

import ast
from pathlib import Path

import pgm_wm

ROOT = Path(pgm_wm.__file__).resolve().parent


def _modules() -> dict[str, Path]:
    mods = {}
    for f in ROOT.rglob("*.py"):
        parts = f.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        mods[name] = f
    return mods


MODULES = _modules()


def _imports(name: str) -> list[tuple[str, str]]:
    """``(target module, imported name)`` for every import of a pgm_wm module in ``name``."""
    f = MODULES[name]
    package = name if f.name == "__init__.py" else name.rsplit(".", 1)[0]
    out = []
    for node in ast.walk(ast.parse(f.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            elif (node.module or "").startswith("pgm_wm"):
                target = node.module
            else:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                out.append((sub, "") if sub in MODULES else (target, alias.name))
        elif isinstance(node, ast.Import):
            out += [(a.name, "") for a in node.names if a.name.startswith("pgm_wm")]
    return out


def _graph() -> dict[str, set[str]]:
    return {m: {t for t, _ in _imports(m) if t in MODULES and t != m} for m in MODULES}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, on, stack, comps, counter = {}, {}, set(), [], [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
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
                comps.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return comps


def _reaches(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for w in graph[todo.pop()]:
            if w not in seen:
                seen.add(w)
                todo.append(w)
    return seen


def test_the_checker_finds_a_cycle_and_a_private_import():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_among_pgm_wm_modules():
    assert _cycles(_graph()) == []


def test_no_module_imports_a_private_name_from_another():
    bad = [(m, t, n) for m in MODULES for t, n in _imports(m)
           if n.startswith("_") and not n.startswith("__") and t != m]
    assert bad == []


def test_layers_follow_the_book():
    graph = _graph()
    # the data layer never pulls in the training loop
    for m in MODULES:
        if m.startswith("pgm_wm.datasets"):
            assert "pgm_wm.training" not in _reaches(graph, m), m
    # chapter 2 (aggregation) does not import chapter 3 (the factorized belief, the RKN)
    assert not {"pgm_wm.factorized", "pgm_wm.rkn"} & _reaches(graph, "pgm_wm.aggregation")
    # the parallel Kalman filter builds on the sequential one, never the reverse
    assert "pgm_wm.kalman_parallel" not in _reaches(graph, "pgm_wm.kalman")
