"""Tests for the data_tools command line (`python -m data_tools info|build`), run as a subprocess."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from data_tools.bundle import load_bundle

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"
TARGET = ROOT / "histojax" / "data" / "CMU-1-Small-Region.target.xml"
BROKEN = ROOT / "tests" / "data" / "broken.svs"


def _run(*args) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "data_tools", *map(str, args)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        encoding="utf-8",
    )


def _one_line_error(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    return lines[0]


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> tuple[Path, subprocess.CompletedProcess]:
    out = tmp_path_factory.mktemp("cli") / "bundle"
    proc = _run("build", SVS, "--annotations", TARGET, "--out", out, "--levels", "3", "--quiet")
    return out, proc


def test_info_slide():
    proc = _run("info", SVS)
    assert proc.returncode == 0, proc.stderr
    for text in ("2220×2967", "240×240", "JPEG", "0.499"):
        assert text in proc.stdout
    assert proc.stderr == ""


def test_build_writes_bundle(built):
    out, proc = built
    assert proc.returncode == 0, proc.stderr
    assert "wrote" in proc.stdout
    assert "Traceback" not in proc.stderr
    b = load_bundle(out)
    assert len(b.pixels) == 3
    assert b.metadata["level_sets"] == [3]
    assert b.tumour[0].sum() > 0


def test_info_bundle_lists_levels(built):
    out, _ = built
    proc = _run("info", out)
    assert proc.returncode == 0, proc.stderr
    assert "CMU-1-Small-Region.svs" in proc.stdout
    for k, size in enumerate(("2220×2967", "555×741", "138×185")):
        assert f"level {k}: {size}" in proc.stdout
    assert "level 3" not in proc.stdout


def test_build_existing_folder_needs_overwrite(built):
    out, _ = built
    proc = _run("build", SVS, "--out", out, "--levels", "3", "--quiet")
    line = _one_line_error(proc)
    assert "--overwrite" in line
    assert str(out) in line
    load_bundle(out)  # still the previous, valid bundle


def test_info_broken_slide():
    proc = _run("info", BROKEN)
    line = _one_line_error(proc)
    assert "broken.svs" in line


@pytest.mark.parametrize("label_map", ["[1]", '{"Tumor": "bogus"}', "{not json"])
def test_bad_label_map(tmp_path, label_map):
    out = tmp_path / "bundle"
    proc = _run(
        "build", SVS, "--annotations", TARGET, "--out", out, "--levels", "3", "--quiet", "--label-map", label_map
    )
    line = _one_line_error(proc)
    assert "--label-map" in line
    assert list(tmp_path.iterdir()) == []


def test_bad_levels_is_usage_error(tmp_path):
    proc = _run("build", SVS, "--out", tmp_path / "bundle", "--levels", "1", "--quiet")
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "--levels" in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_build_quiet_prints_one_line(built):
    """``build --quiet``: the one ``wrote ...`` line, no level table (``info BUNDLE`` prints it); before, the table
    came with it."""
    _, proc = built
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines() == [proc.stdout.strip()] and proc.stdout.startswith("wrote "), proc.stdout
