"""The `histojax` console entry point: dispatch, help, one-line errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"


def run(*args):
    return subprocess.run(
        [sys.executable, "-m", "histojax.cli", *args], cwd=ROOT, capture_output=True, text=True, timeout=300
    )


def test_help_lists_the_subcommands():
    out = run("--help")
    assert out.returncode == 0
    for command in ("info", "build", "features", "demo", "train", "evaluate", "bench"):
        assert f"histojax {command}" in out.stdout


def test_help_is_plain_text_without_rest_markup(capsys):
    """Was: ``histojax --help`` printed its docstring's reST (double backticks, :func: roles) as it is."""
    import pytest

    from baselines.reading import readers
    from histojax.cli import main

    assert main(["--help"]) == 0
    text = capsys.readouterr().out
    assert "python -m data_tools <command>" in text and "own_package_refusal" in text
    with pytest.raises(SystemExit):
        readers.main(["--help"])  # a command's description: its module doc's first paragraph
    text += capsys.readouterr().out
    for markup in ("``", ":func:", ":mod:", ":class:", ":meth:"):
        assert markup not in text


def test_info_dispatches_to_data_tools():
    out = run("info", str(SVS))
    assert out.returncode == 0 and "2220×2967" in out.stdout


def test_user_errors_are_one_line_without_traceback(tmp_path):
    for args in (
        ["info", str(ROOT / "tests" / "data" / "broken.svs")],
        ["frobnicate"],
        ["demo", "--steps", "notanumber"],
    ):
        out = run(*args)
        assert out.returncode == 2, args
        assert "Traceback" not in out.stderr
        assert len([line for line in out.stderr.splitlines() if "error:" in line]) == 1


def test_build_then_info_on_the_bundle(tmp_path):
    out = run("build", str(SVS), "--out", str(tmp_path / "b"), "--levels", "3", "--quiet")
    assert out.returncode == 0, out.stderr
    info = run("info", str(tmp_path / "b"))
    assert info.returncode == 0 and "level 2" in info.stdout


def test_every_command_is_a_module_with_one_parser():
    """Each `histojax <command>` is its module's add_arguments (the options, declared once) and run."""
    import importlib

    from histojax.cli import ALGOS, COMMANDS

    for module_name in [*COMMANDS.values(), *(f"baselines.{algo}" for algo in ALGOS)]:
        module = importlib.import_module(module_name)
        assert callable(module.add_arguments) and callable(module.run), module_name
    for command in ("rotation", "budget-curve", "reproduce"):
        assert COMMANDS[command].startswith("baselines.")
    out = run("rotation", "--seeds", "1")
    assert out.returncode == 2 and out.stderr.strip() == (
        "error: histojax rotation: --budget-mb is required (--help shows the options)"
    )
