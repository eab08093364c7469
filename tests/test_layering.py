"""The package's modules import each other without cycles (docs/design.md's layering): a
module low in the spine (raw, grid, render) never reaches up to one above it (train, cli)."""

import ast
from pathlib import Path

import gridnerf

PACKAGE = Path(gridnerf.__file__).parent


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, modules: set[str]) -> set[str]:
    """The package modules `path` imports anywhere in it (module level or in a function)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:  # a submodule, else a name the module defines
                sub = f"{node.module}.{alias.name}"
                found |= {sub} & modules or {node.module} & modules
    return found - {"gridnerf"}


def import_graph() -> dict[str, set[str]]:
    paths = sorted(PACKAGE.rglob("*.py"))
    modules = {module_name(p) for p in paths}
    return {module_name(p): imports_of(p, modules) - {module_name(p)} for p in paths}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as [a, b, ..., a], or None (depth-first search, three colours)."""
    state, stack = {}, []

    def visit(node):
        state[node] = "open"
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == "open":
                return stack[stack.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        state[node] = "done"
        stack.pop()
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            return cycle
    return None


def test_find_cycle_sees_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set(), "c": {"a", "b"}}) is None


def test_the_package_has_no_import_cycle():
    graph = import_graph()
    assert {"gridnerf.train", "gridnerf.grid", "gridnerf.cli"} <= set(graph)
    assert "gridnerf.grid" in graph["gridnerf.train"]  # the parser sees `from gridnerf import`
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


# what a training run imports must not reach evaluation or the simulator: a capture is
# trained from its files alone, and what eval measures cannot steer the fit
TRAINING_ROOTS = ("gridnerf.train",)
FORBIDDEN_IN_TRAINING = ("gridnerf.eval_run", "gridnerf.evaluate", "gridnerf.sim")


def reachable(graph: dict[str, set[str]], roots) -> set[str]:
    """Every module the roots import, directly or through others (the roots included)."""
    seen, todo = set(), list(roots)
    while todo:
        node = todo.pop()
        if node not in seen:
            seen.add(node)
            todo += sorted(graph.get(node, ()))
    return seen


def forbidden(modules: set[str]) -> list[str]:
    return sorted(m for m in modules
                  if any(m == f or m.startswith(f + ".") for f in FORBIDDEN_IN_TRAINING))


def test_reachable_and_forbidden_see_an_indirect_import():
    graph = {"gridnerf.train": {"gridnerf.a"}, "gridnerf.a": {"gridnerf.sim.sensor"},
             "gridnerf.sim.sensor": set()}
    assert forbidden(reachable(graph, TRAINING_ROOTS)) == ["gridnerf.sim.sensor"]
    assert forbidden({"gridnerf.simple", "gridnerf.eval_runner"}) == []


def test_the_training_path_imports_neither_evaluation_nor_the_simulator():
    graph = import_graph()
    path = reachable(graph, TRAINING_ROOTS)
    assert {"gridnerf.optim", "gridnerf.methods.brightnerf", "gridnerf.plan"} <= path
    assert forbidden(path) == [], forbidden(path)
