"""A wheel that installs: the package data the code opens is declared in pyproject.toml (fast), and a
wheel built from the tree, installed into a fresh venv and run from outside the source tree, installs only the
top-level packages the ``histojax`` command needs, reaches the published agents by name, and runs the README's
quick start and ``histojax demo --no-train`` from an empty folder (slow, ``make test-all``)."""

from __future__ import annotations

import fnmatch
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[2]
# what the code opens through Path(__file__) / importlib.resources: every wheel must carry these
REQUIRED = (
    "histojax/data/CMU-1-Small-Region.svs",
    "histojax/data/CMU-1-Small-Region.target.xml",
    "data_tools/features/pcam_cnn.msgpack",
    "data_tools/features/pcam_cnn.json",
    "data_tools/features/pcam_cnn96.msgpack",
    "data_tools/features/pcam_cnn96.json",
    "data_tools/pcam/bank.npz",
    "data_tools/camelyon16/tumor_009.xml",
    "data_tools/camelyon16/bench_normal_004.xml",
    "data_tools/camelyon16/ncrf/Tumor_072.json",
    "baselines/published/c16-v2-head/config.json",
    "histojax/py.typed",
)
TOP_LEVEL = {"histojax", "data_tools", "baselines"}  # benchmarks/ and experiments/ run from the repository only


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _source_files() -> list[str]:
    """The tree's files as a clean clone has them (tracked plus untracked, not ignored), POSIX paths."""
    out = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split("\n")
    return [f for f in out if f and (ROOT / f).is_file()]


def _glob_match(rel: str, pattern: str) -> bool:
    """setuptools' package-data match: ``*`` within one path segment, the same number of segments."""
    parts, pat = rel.split("/"), pattern.split("/")
    return len(parts) == len(pat) and all(fnmatch.fnmatchcase(a, b) for a, b in zip(parts, pat))


def _package_dirs() -> set[str]:
    """Folders of the packages ``[tool.setuptools.packages.find] include`` selects (those with __init__.py)."""
    include = _pyproject()["tool"]["setuptools"]["packages"]["find"]["include"]
    dirs = {str(Path(f).parent.as_posix()) for f in _source_files() if f.endswith("/__init__.py")}
    return {d for d in dirs if any(fnmatch.fnmatchcase(d.replace("/", "."), g) for g in include)}


def _declared(path: str, package_data: dict) -> bool:
    """Whether file ``path`` is matched by a package-data glob of one of its enclosing packages."""
    for pkg, globs in package_data.items():
        base = pkg.replace(".", "/") + "/"
        if path.startswith(base) and any(_glob_match(path[len(base) :], g) for g in globs):
            return True
    return False


def test_package_data_declares_every_data_file():
    package_data = _pyproject()["tool"]["setuptools"]["package-data"]
    packages = _package_dirs()
    top = {d.split("/")[0] for d in packages}
    data = [
        f
        for f in _source_files()
        if f.split("/")[0] in top and not f.endswith((".py", ".pyc")) and "__pycache__" not in f
    ]
    for required in REQUIRED:
        assert required in data, f"{required} is not in the source tree"
    undeclared = [f for f in data if not _declared(f, package_data)]
    assert not undeclared, f"not in pyproject.toml's [tool.setuptools.package-data], so not in the wheel: {undeclared}"


def test_package_data_check_can_fail():
    package_data = {**_pyproject()["tool"]["setuptools"]["package-data"], "data_tools": ["camelyon16/*"]}
    assert not _declared("data_tools/pcam/bank.npz", package_data)
    assert _declared("data_tools/camelyon16/tumor_009.xml", package_data)
    assert not _declared("data_tools/camelyon16/ncrf/Tumor_072.json", package_data)  # * stays in its folder


def _readme_quick_start() -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Quick start", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_wheel_installs_and_runs_outside_the_tree(tmp_path):
    """Build the wheel from a copy of the tree, install it (no deps) into a fresh venv whose only other path
    is this venv's site-packages (the dependencies; its editable histojax finder is not activated: a
    folder added by a .pth is not a site folder), then run the README's quick start and the demo's
    random-agent table from a folder outside the tree."""
    src = tmp_path / "src"
    for f in _source_files():
        (src / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / f, src / f)
    wheels = tmp_path / "wheels"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "-q", "-w", str(wheels)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    (wheel,) = wheels.glob("histojax-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    missing = [f for f in REQUIRED if f not in names]
    assert not missing, f"the wheel lacks {missing}"
    top = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert top == TOP_LEVEL, f"the wheel's top-level names are {sorted(top)}, not {sorted(TOP_LEVEL)}"
    assert any(n.endswith(".dist-info/LICENSE") or n.endswith(".dist-info/licenses/LICENSE") for n in names)

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    r = subprocess.run(
        [sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "--no-index", "-q", str(wheel)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    (Path(site) / "histojax_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")

    run_dir = tmp_path / "elsewhere"
    run_dir.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")}
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    where = subprocess.run(
        [
            str(py),
            "-c",
            "import histojax, data_tools, baselines; print(histojax.__file__); "
            "print(data_tools.__file__); print(baselines.__file__)",
        ],
        cwd=run_dir,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert where.returncode == 0, where.stderr[-3000:]
    for line in where.stdout.split():
        assert Path(line).is_relative_to(venv), f"imported from outside the installed wheel: {line}"
    absent = subprocess.run(
        [str(py), "-c", "import importlib.util as u; print(u.find_spec('benchmarks'), u.find_spec('experiments'))"],
        cwd=run_dir,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert absent.stdout.split() == ["None", "None"], absent.stdout + absent.stderr[-3000:]

    histojax_command = str(venv / "bin" / "histojax")
    r = subprocess.run(
        [histojax_command, "published"], cwd=run_dir, env=env, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr[-3000:]
    published = sorted(p.name for p in (ROOT / "baselines" / "published").iterdir() if p.is_dir())
    listed = [line.split()[0] for line in r.stdout.splitlines()[3:] if line.strip()]
    assert listed == published and str(venv) in r.stdout.splitlines()[0], r.stdout
    r = subprocess.run(
        [histojax_command, "evaluate", "c16-v2-set-reader"],
        cwd=run_dir,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )  # found by name; without --dataset: refused
    assert r.returncode == 2 and f"{Path(site) / 'baselines' / 'published' / 'c16-v2-set-reader'}" in r.stderr, (
        r.stderr[-3000:]
    )
    assert "a published agent; its config.json records no path" in r.stderr, r.stderr[-3000:]
    r = subprocess.run([histojax_command, "bench"], cwd=run_dir, env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and "histojax bench runs from a source checkout" in r.stderr, r.stderr[-3000:]

    r = subprocess.run(
        [str(py), "-c", _readme_quick_start()], cwd=run_dir, env=env, capture_output=True, text=True, timeout=600
    )
    assert r.returncode == 0, r.stderr[-3000:]
    empty = tmp_path / "empty"
    empty.mkdir()
    r = subprocess.run(
        [histojax_command, "demo", "--no-train", "--out", "demo-out"],
        cwd=empty,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert "HistoJAX-Easy-v0" in r.stdout and (empty / "demo-out" / "demo_trajectory.png").is_file()
