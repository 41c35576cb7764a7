"""The import graph points one way: no circles, and no import from a higher floor.

Floors, lowest first: ``data_tools`` → ``histojax`` → ``baselines`` → ``benchmarks`` → ``experiments`` (the
experiment drivers: they may import any floor, nothing imports them). Every ``.py`` file of the
five packages is parsed with :mod:`ast` and every import counts, including imports inside functions (they hide
circles as well as top-level ones). ``from pkg import name`` is an edge to ``pkg.name`` when that is a module
of the repository, else to ``pkg`` itself. The implicit import of a parent package (``import a.b`` runs
``a/__init__``) is not counted: every package's ``__init__`` imports its own modules, and counting it would make
every package a circle.

Inside ``histojax``, the env core (``histojax.core``) is a floor under the reading stack (``histojax.reading``):
no core module imports it, and ``histojax.make`` reaches no reading module on its way to the jitted step.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
FLOORS = ("data_tools", "histojax", "baselines", "benchmarks", "experiments")


def _modules(root: pathlib.Path = ROOT) -> dict[str, pathlib.Path]:
    """``{dotted module name: file}`` of every ``.py`` under the five packages (a package is its ``__init__``)."""
    out = {}
    for top in FLOORS:
        for path in sorted((root / top).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _resolve(name: str, modules: dict) -> str | None:
    """The longest prefix of ``name`` that is a module of the repository (``None`` if none is)."""
    parts = name.split(".")
    while parts:
        cand = ".".join(parts)
        if cand in modules:
            return cand
        parts.pop()
    return None


def import_graph(root: pathlib.Path = ROOT) -> dict[str, dict[str, int]]:
    """``{module: {imported module: line of the first such import}}`` over the repository's five packages."""
    modules = _modules(root)
    graph = {}
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        edges: dict[str, int] = {}
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    src = ".".join(base + ([node.module] if node.module else []))
                else:
                    src = node.module or ""
                targets = [f"{src}.{a.name}" if f"{src}.{a.name}" in modules else src for a in node.names]
            for t in targets:
                r = _resolve(t, modules)
                if r is not None and r != mod:
                    edges.setdefault(r, node.lineno)
        graph[mod] = edges
    return graph


def find_cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
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


def _floor(mod: str) -> int:
    return FLOORS.index(mod.split(".")[0])


def test_graph_sees_imports_inside_functions(tmp_path):
    """The parser counts a circle hidden in a function, so the tests below can fail."""
    pkg = tmp_path / "histojax"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from histojax import b\n")
    (pkg / "b.py").write_text("def f():\n    from . import a\n    return a\n")
    for top in FLOORS[::2] + ("benchmarks",):
        (tmp_path / top).mkdir(exist_ok=True)
    (tmp_path / "data_tools" / "x.py").write_text("def g():\n    import histojax.a\n")
    graph = import_graph(tmp_path)
    assert find_cycles(graph) == [["histojax.a", "histojax.b"]]
    assert "histojax.a" in graph["data_tools.x"]


def test_no_import_circles():
    cycles = find_cycles(import_graph())
    assert not cycles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_imports_point_down_the_floors():
    """data_tools → histojax → baselines → benchmarks → experiments: nothing imports a higher floor."""
    modules = _modules()
    up = [
        f"{modules[m].relative_to(ROOT)}:{line}: {m} imports {t}"
        for m, edges in import_graph().items()
        for t, line in edges.items()
        if _floor(t) > _floor(m)
    ]
    assert not up, "imports from a higher floor:\n" + "\n".join(up)


def _reach(graph: dict[str, dict[str, int]], start: str) -> dict[str, list[str]]:
    """``{module: the import path from start to it}`` of every module ``start`` imports, directly or not."""
    paths, todo = {start: [start]}, [start]
    while todo:
        m = todo.pop()
        for t in graph.get(m, ()):
            if t not in paths:
                paths[t] = paths[m] + [t]
                todo.append(t)
    return paths


def test_env_core_imports_nothing_from_the_reading_stack():
    """The env core (``histojax.core``: the env, its step modules and the navigation and observation modes) is a
    floor under the reading stack: no core module imports ``histojax.reading``, directly or through another
    module (the reading modes register themselves into the core's mode names instead)."""
    graph = import_graph()
    core = [m for m in graph if m == "histojax.core" or m.startswith("histojax.core.")]
    assert "histojax.core.env" in core and "histojax.core.modes.factory" in core
    up = [
        f"{m} imports {t}"
        for m in core
        for t in graph[m]
        if t == "histojax.reading" or t.startswith("histojax.reading.")
    ]
    assert not up, "the env core imports the reading stack:\n" + "\n".join(up)


@pytest.mark.parametrize("start", ["histojax.registry", "histojax.core.env"])
def test_make_to_the_jitted_step_meets_no_reading_module(start):
    """``histojax.make`` (the registry) and the env it makes reach, through every import, no module of the reading
    stack: a reader following ``make`` to ``step`` stays on the core floor."""
    reached = _reach(import_graph(), start)
    bad = [" -> ".join(p) for m, p in reached.items() if m.startswith("histojax.reading")]
    assert not bad, "reaches the reading stack:\n" + "\n".join(bad)


def test_the_core_rule_can_fail(tmp_path):
    """An upward import hidden in a function of a core module is seen, so the two tests above can fail."""
    for top in FLOORS:
        (tmp_path / top).mkdir()
    core, reading = tmp_path / "histojax" / "core", tmp_path / "histojax" / "reading"
    core.mkdir()
    reading.mkdir()
    for d in (tmp_path / "histojax", core, reading):
        (d / "__init__.py").write_text("")
    (reading / "glimpse.py").write_text("from histojax.core import env\n")
    (core / "env.py").write_text("def f():\n    from histojax.reading import glimpse\n    return glimpse\n")
    graph = import_graph(tmp_path)
    assert "histojax.reading.glimpse" in graph["histojax.core.env"]
    assert "histojax.reading.glimpse" in _reach(graph, "histojax.core.env")


@pytest.mark.parametrize("floor", FLOORS)
def test_every_floor_is_parsed(floor):
    assert any(m.split(".")[0] == floor for m in import_graph())


def _folder_edges(graph: dict[str, dict[str, int]], src: str, dst: str) -> list[str]:
    """``module imports module`` for every import from a module of package ``src`` to one of package ``dst``."""

    def inside(m, pkg):
        return m == pkg or m.startswith(pkg + ".")

    return [f"{m} imports {t}" for m, edges in graph.items() if inside(m, src) for t in edges if inside(t, dst)]


@pytest.mark.parametrize(
    "upper, lower",
    [
        ("baselines.evaluate", "baselines.reading"),
        ("baselines.evaluate", "baselines.episodes"),
        ("baselines.reading", "baselines.episodes"),
    ],
)
def test_baselines_folders_import_one_way(upper, lower):
    """``baselines.evaluate`` → ``baselines.reading`` → ``baselines.episodes`` (the policies and their episodes,
    which both run): a lower folder imports nothing of a higher one, so the two commands' folders are no circle of
    folders even where no module circle shows."""
    graph = import_graph()
    assert any(m.startswith(lower + ".") for m in graph), f"{lower} has no modules"
    back = _folder_edges(graph, lower, upper)
    assert not back, f"{lower} imports {upper}, which imports it:\n" + "\n".join(back)
