"""The import graph points one way: no circles, and no import from a higher floor.

Floors, lowest first: ``data_tools`` → ``histojax`` → ``baselines`` → ``benchmarks`` → ``experiments`` (the
experiment drivers: they may import any floor, nothing imports them). Every ``.py`` file of the
five packages is parsed with :mod:`ast` and every import counts, including imports inside functions (they hide
circles as well as top-level ones). ``from pkg import name`` is an edge to ``pkg.name`` when that is a module
of the repository, else to ``pkg`` itself. The implicit import of a parent package (``import a.b`` runs
``a/__init__``) is not counted: every package's ``__init__`` imports its own modules, and counting it would make
every package a circle.

Inside ``histojax``, the env core (``histojax.core``) is a floor under the reading stack (``histojax.reading``):
no core module imports it, and ``histojax.make`` reaches no reading module on its way to the jitted step. The core
touches no file either: it imports no module of the repository outside ``histojax.core`` (not ``data_tools``, not
``histojax.loading`` nor the front door), no module that reads or writes files (``pathlib``, ``os``, ``mmap``,
``ctypes``, ``json``, ``tifffile``, ...) and calls no ``open`` or ``np.load``; loading a bundle is ``histojax.loading``.
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


# modules that read or write files (or the process's memory mappings): no module of the env core imports one
FILE_MODULES = (
    "pathlib", "os", "io", "mmap", "ctypes", "json", "shutil", "tempfile", "glob", "pickle", "gzip", "tarfile",
    "zipfile", "csv", "sqlite3", "fcntl", "tifffile", "h5py", "PIL", "openslide", "pydicom", "zarr",
)  # fmt: skip
# the one host-side helper of the core that reaches a file-touching module: ``HistoEnv.render`` (gymnax's render API,
# never called by the step) imports the renderer inside the method, when a picture is asked for
HOST_HELPERS = {("histojax.core.env", "histojax.render")}
# calls that open a file: the builtin ``open`` and numpy's file readers and writers
FILE_CALLS = ("open", "load", "save", "savez", "savez_compressed", "memmap", "fromfile", "tofile", "loadtxt")


def _core_files(root: pathlib.Path = ROOT) -> dict[str, pathlib.Path]:
    """``{module: file}`` of every module of ``histojax.core`` under ``root``."""
    return {m: p for m, p in _modules(root).items() if m == "histojax.core" or m.startswith("histojax.core.")}


def core_file_access(root: pathlib.Path = ROOT) -> list[str]:
    """Every import or call of a ``histojax.core`` module under ``root`` that can touch a file, one
    ``"file:line: what"`` each: a repository module outside the core (``data_tools``, ``histojax.loading``,
    ``histojax.registry``, ...), a module of :data:`FILE_MODULES` (``os.path`` counts as ``os``), a call of the
    builtin ``open`` or of ``np.load``-like :data:`FILE_CALLS` on ``np`` / ``numpy`` / ``jnp``; imports inside
    functions count (but for the one host-side helper of :data:`HOST_HELPERS`, which may import its module inside a
    function, not at the top of the file)."""
    modules = _modules(root)
    graph = import_graph(root)
    out = []
    for mod, path in _core_files(root).items():
        rel = path.relative_to(root)
        tree = ast.parse(path.read_text(), str(path))
        top_level = {n.lineno for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))}
        for t, line in graph[mod].items():
            if (mod, t) in HOST_HELPERS and line not in top_level:
                continue  # imported inside the host-side helper only
            if not (t == "histojax.core" or t.startswith("histojax.core.")):
                out.append(f"{rel}:{line}: imports {t} (outside the core)")
        for node in ast.walk(tree):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names = [node.module]
            for name in names:
                if name.split(".")[0] in FILE_MODULES or (
                    name.split(".")[0] in ("data_tools",) and name not in modules
                ):
                    out.append(f"{rel}:{node.lineno}: imports {name}")
            if isinstance(node, ast.Call):
                f = node.func
                if isinstance(f, ast.Name) and f.id == "open":
                    out.append(f"{rel}:{node.lineno}: calls open")
                elif (
                    isinstance(f, ast.Attribute)
                    and f.attr in FILE_CALLS
                    and isinstance(f.value, ast.Name)
                    and f.value.id in ("np", "numpy", "jnp")
                ):
                    out.append(f"{rel}:{node.lineno}: calls {f.value.id}.{f.attr}")
    return out


def test_env_core_touches_no_file():
    """Nothing under ``histojax/core/`` imports ``data_tools``, ``histojax.loading``, the front door or any other
    repository module outside the core, nor a file-touching module, nor opens a file: the core is the pure step and
    ``SlideArrays``; reading bundles from disk is :mod:`histojax.loading` (on main before this rule,
    ``histojax/core/slide.py`` imported ``data_tools.bundle_files`` and ``pathlib`` and memory-mapped bundles)."""
    assert "histojax.core.slide" in _core_files()
    bad = core_file_access()
    assert not bad, "the env core touches files:\n" + "\n".join(bad)


def test_the_file_rule_can_fail(tmp_path):
    """Each kind of file access the rule names is seen, inside functions too, so the test above can fail."""
    for top in FLOORS:
        (tmp_path / top).mkdir()
    core = tmp_path / "histojax" / "core"
    core.mkdir()
    for d in (tmp_path / "histojax", core, tmp_path / "data_tools"):
        (d / "__init__.py").write_text("")
    (tmp_path / "histojax" / "loading.py").write_text("")
    (tmp_path / "data_tools" / "errors.py").write_text("")
    (core / "slide.py").write_text(
        "import numpy as np\n"
        "from data_tools.errors import E\n"
        "def f(p):\n"
        "    import mmap, os.path\n"
        "    from pathlib import Path\n"
        "    from histojax import loading\n"
        "    return open(p), np.load(p), mmap, os, Path, loading, E\n"
    )
    (tmp_path / "histojax" / "render.py").write_text("")
    (core / "env.py").write_text("from histojax.core import slide\ndef render():\n    from histojax import render\n")
    (core / "views.py").write_text("from histojax import render\n")
    found = "\n".join(core_file_access(tmp_path))
    for what in (
        "imports data_tools.errors (outside",
        "imports mmap",
        "imports os.path",
        "imports pathlib",
        "imports histojax.loading (outside",
        "calls open",
        "calls np.load",
    ):
        assert what in found, what
    assert "env.py" not in found  # its render helper imports the renderer inside the method
    assert "views.py:1: imports histojax.render (outside" in found  # a top-level import of it is not exempt
