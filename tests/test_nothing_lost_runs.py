"""Nothing lost where users work, the reading and training side: every reader of a bundle in baselines.reading goes
through the checked bundle loader, head folders are read through one guarded reader (strict types, bounded sizes and
structure, no blocking, one line instead of a traceback), the budget curve's options are checked, undefined results
say so, run folders are never overwritten silently and hold one writer at a time, and the words of the evaluate /
train commands.

The head tools read a small feature-only stand-in dataset (tests/test_head.py's, with checksums and a sealed
metadata.json as a build writes them)."""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from baselines.reading import head_fit, head_mil_fit, readers
from data_tools.errors import HistojaxDataError
from test_head import make_dataset

ROOT = Path(__file__).resolve().parents[1]


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), err
    return lines[0]


# ----------------------------------------------------------------------------- every reader of a bundle is checked
@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("runs-ds"), n_train=6, n_test=2)


@pytest.fixture()
def work(small_dataset, tmp_path):
    dest = tmp_path / "ds"
    shutil.copytree(small_dataset, dest)
    return dest


def _first_bundle(ds: Path) -> Path:
    return ds / json.loads((ds / "dataset.json").read_text())["train"][0]


def _link_outside(ds: Path, tmp_path: Path) -> Path:
    bundle = _first_bundle(ds)
    outside = tmp_path / "OUTSIDE.npy"
    np.save(outside, np.full(np.load(bundle / "features_00.npy").shape, 9.0, np.float16))
    (bundle / "features_00.npy").unlink()
    (bundle / "features_00.npy").symlink_to(outside)
    return bundle


def _absolute_path_in_metadata(ds: Path, tmp_path: Path) -> Path:
    bundle = _first_bundle(ds)
    meta = json.loads((bundle / "metadata.json").read_text())
    shutil.copy(bundle / "features_00.npy", tmp_path / "elsewhere.npy")
    meta["features"]["levels"][0]["file"] = str(tmp_path / "elsewhere.npy")
    (bundle / "metadata.json").write_text(json.dumps(meta))
    return bundle


def _flip_a_feature(ds: Path, tmp_path: Path) -> Path:
    bundle = _first_bundle(ds)
    a = np.load(bundle / "features_00.npy")
    a[0, 0, 62] = 7.0
    np.save(bundle / "features_00.npy", a)
    return bundle


@pytest.mark.parametrize("damage, words", [(_link_outside, "symbolic link"),
                                            (_absolute_path_in_metadata, "metadata"),
                                            (_flip_a_feature, "checksum mismatch")])
def test_the_head_tools_read_bundles_through_the_checked_loader(work, tmp_path, damage, words):
    bundle = damage(work, tmp_path)
    for read in (lambda: head_fit.load_slide(bundle), lambda: head_mil_fit.load_grid(bundle),
                 lambda: head_fit.load_slides(work, "train")):
        with pytest.raises(HistojaxDataError) as e:
            read()
        assert words in str(e.value) and str(bundle) in str(e.value), e.value


def test_head_fit_refuses_a_linked_feature_grid_in_one_line(work, tmp_path, capsys):
    _link_outside(work, tmp_path)
    assert head_fit.main(["--dataset", str(work), "--out", str(tmp_path / "head")]) == 2
    assert "symbolic link" in _one_line(capsys)
    assert not (tmp_path / "head").exists()


def test_readers_cell_level_reads_the_checked_metadata(work, tmp_path):
    bundle = _first_bundle(work)
    meta = json.loads((bundle / "metadata.json").read_text())
    meta["levels"][1]["downsample"] = 3.0  # edited after the build: the seal no longer matches
    (bundle / "metadata.json").write_text(json.dumps(meta))
    spec = head_fit.read_spec(work)
    with pytest.raises(HistojaxDataError, match="digest mismatch"):
        readers.cell_level_for(work, spec, "train")
