"""The project's import graph: no cycles, deferred imports inside functions included, and
the physics free of the learning stack."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: import name of each source folder (setuptools' package-dir mapping in pyproject.toml)
PACKAGES = {"heml_gym": ROOT / "heml_gym", "heml_gym.envs": ROOT / "envs", "heml_gym.agents": ROOT / "agents",
            "heml_gym.benchmarks": ROOT / "benchmarks"}
LAYERS_ABOVE_PHYSICS = ("heml_gym.envs", "heml_gym.agents", "heml_gym.benchmarks")


def modules() -> dict[str, tuple[Path, bool]]:
    """Every module of the project: import name -> (file, is a package's __init__)."""
    found = {}
    for package, folder in PACKAGES.items():
        for path in folder.rglob("*.py"):
            parts = [p for p in path.relative_to(folder).with_suffix("").parts if p != "__init__"]
            found[".".join([package, *parts])] = (path, path.name == "__init__.py")
    return found


def import_graph() -> dict[str, set[str]]:
    """Module -> the project modules it imports, at the top or inside a function. A
    module's own parent packages are left out: Python initialises them before it, so
    ``from . import x`` in a package's module does not make a cycle with the package."""
    mods = modules()
    graph = {}
    for name, (path, is_package) in mods.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if is_package else name.split(".")[:-1]
                    base = base[:len(base) - node.level + 1]
                    module = ".".join(base + ([node.module] if node.module else []))
                else:
                    module = node.module
                targets.update(f"{module}.{a.name}" for a in node.names)  # (submodules)
                if node.module:
                    targets.add(module)
        graph[name] = {t for t in targets if t in mods and t != name and not name.startswith(t + ".")}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_checker_finds_a_cycle_through_a_deferred_import():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(graph) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles_in_the_project():
    graph = import_graph()
    assert len(graph) > 50  # every folder was read
    assert cycles(graph) == []


def test_the_physics_imports_no_learning_or_visualisation_library():
    """heml_gym's physics depends on numpy, numba, scipy, meshio (and gmsh for organs):
    never on gymnasium, torch, SB3, rerun or Ray, at the top or inside a function."""
    banned = ("gymnasium", "torch", "stable_baselines3", "rerun", "ray", *LAYERS_ABOVE_PHYSICS)
    offenders = []
    for name, (path, _) in modules().items():
        if name.startswith(LAYERS_ABOVE_PHYSICS):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) and not node.level else [])
            offenders += [f"{name}: {n}" for n in names if n.split(".")[0] in banned or n.startswith(banned)]
    assert offenders == []


def numba_kernels() -> list[tuple[str, str, int]]:
    """``(module, function, number of arguments)`` of every ``@njit`` / ``@jit`` function of
    the physics and the envs."""
    found = []
    for name, (path, _) in modules().items():
        if name.startswith(("heml_gym.agents", "heml_gym.benchmarks")):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef) and any("jit" in ast.unparse(d) for d in node.decorator_list):
                found.append((name, node.name, len(node.args.args) + len(node.args.kwonlyargs)))
    return found


def test_no_kernel_takes_more_than_twenty_arguments():
    """Kernels take bundles (heml_gym.kernel_data and the solvers' own NamedTuples), not
    dozens of positional arrays."""
    kernels = numba_kernels()
    assert len(kernels) > 100  # every kernel module was read
    assert [k for k in kernels if k[2] > 20] == []
