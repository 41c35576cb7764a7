"""The cohort path's safety on the C16 path: ``python -m data_tools c16`` builds each bundle into a hidden
``bundles/.NAME.tmp-*`` and swaps it in once whole, so a failed rebuild (the disk full while the bundle is
written, or while a feature grid is added to a built set) leaves the previous bundle and its record as they
were, a ``dataset.json`` that failures would leave with no test slide (or no slide) is not written over the
previous one, and the next run rebuilds. Two normal slides of the ``--small`` set (their own tissue, seconds to
build: one on each side of the split); features from the tiny test encoder of tests/encoder_helpers.py."""

from __future__ import annotations

import errno
import json
from pathlib import Path

import numpy as np
import pytest

from data_tools.bundle_files.reading import load_bundle, read_metadata
from data_tools.errors import HistojaxDataError

NAME = "Normal_042"  # a slide of SMALL_SLIDES, train side at seeds 0 and 1
TEST_NAME = "Normal_108"  # test side at seed 0
TINY = "encoder_helpers:tiny_colour"


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = tmp_path_factory.mktemp("c16staged") / "c16"
    make_c16_dataset(out, small=True, names=[NAME, TEST_NAME], progress=False)
    return out


def _copy(built: Path, tmp_path: Path) -> Path:
    import shutil

    return Path(shutil.copytree(built, tmp_path / "c16"))


def _state(out: Path, name: str = NAME) -> tuple[dict, bytes]:
    """Every file of the slide's bundle (name -> bytes) and its record's bytes."""
    bundle = out / "bundles" / name
    files = {p.name: p.read_bytes() for p in sorted(bundle.iterdir()) if p.is_file()}
    return files, (out / "records" / f"{name}.json").read_bytes()


def _full_disk_after_first(monkeypatch, module, attr: str, inside: str) -> list:
    """Patch ``module.attr`` (a writer called with a path first) so that the first file written under a path
    holding ``inside`` is written, and every later one fails with ENOSPC (as ``np.save`` raises on a full
    disk: no file named). Returns the list of paths it was asked to write."""
    real = getattr(module, attr)
    calls = []

    def writer(file, *args, **kwargs):
        if inside in str(file):
            calls.append(str(file))
            if len(calls) > 1:
                raise OSError(errno.ENOSPC, "No space left on device")
        return real(file, *args, **kwargs)

    monkeypatch.setattr(module, attr, writer)
    return calls


def _check_kept(out: Path, before: tuple[dict, bytes], name: str = NAME) -> None:
    bundle = out / "bundles" / name
    assert _state(out, name) == before  # before: the bundle removed and its record deleted
    load_bundle(bundle)  # whole and verified
    failure = json.loads((out / "records" / "failed" / f"{name}.json").read_text())
    reason = failure["reason"]
    assert f"bundles/{name}" in reason and "No space left on device" in reason and ".tmp-" not in reason
    assert failure["previous_kept"] is True
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob(".*lock"))  # nothing half-written left


def test_a_failed_rebuild_keeps_the_previous_bundle_and_its_record(built, tmp_path, monkeypatch):
    """Another seed remakes the slide, so its bundle is written again; the disk fills after the bundle
    writer's first file. Then, the disk freed, a rerun builds and swaps in the new bundle."""
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = _copy(built, tmp_path)
    before, index = _state(out), (out / "dataset.json").read_bytes()
    calls = _full_disk_after_first(monkeypatch, np, "save", inside="/bundles/")
    with pytest.raises(HistojaxDataError, match=f"no slide of this set is built: 1 failed \\({NAME}: .*No space"):
        make_c16_dataset(out, small=True, names=[NAME], seed=1, progress=False)
    assert len(calls) == 2  # the writer wrote one file into the staged bundle, then the disk was full
    _check_kept(out, before)
    assert (out / "dataset.json").read_bytes() == index  # before: rewritten with no slide

    monkeypatch.undo()
    again = make_c16_dataset(out, small=True, names=[NAME], seed=1, progress=False)
    assert again["run"]["built"] == [NAME] and not again["run"]["failed"]
    assert json.loads((out / "records" / f"{NAME}.json").read_text())["settings"]["seed"] == 1
    assert (
        read_metadata(out / "bundles" / NAME)["metadata_sha256"]
        != json.loads(before[0]["metadata.json"])["metadata_sha256"]
    )
    assert not (out / "records" / "failed" / f"{NAME}.json").exists()
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob(".*lock"))


def test_adding_features_that_fail_leaves_the_pixel_bundle_untouched(built, tmp_path, monkeypatch):
    """A built set given ``--features``: the up-to-date bundle is hard-linked into the staged folder and the
    grid computed there; the disk fills after the first feature chunk. The old bundle's files (the very
    inodes the staged folder shared) are unchanged, and the rerun adds the grid, the old files still whole."""
    import data_tools.features.grid as grid
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = _copy(built, tmp_path)
    before = {n: _state(out, n) for n in (NAME, TEST_NAME)}
    index = (out / "dataset.json").read_bytes()
    calls = _full_disk_after_first(monkeypatch, grid, "save_array", inside="/bundles/")
    with pytest.raises(HistojaxDataError, match=f"the test split would hold no slide.*{TEST_NAME}: .*No space"):
        make_c16_dataset(out, small=True, names=[NAME, TEST_NAME], features=TINY, progress=False)
    assert len(calls) == 3  # one chunk written, then the disk full for each slide
    for n in (NAME, TEST_NAME):
        _check_kept(out, before[n], n)
        assert read_metadata(out / "bundles" / n).features is None
    assert (out / "dataset.json").read_bytes() == index  # before: rewritten with no slide

    monkeypatch.undo()
    again = make_c16_dataset(out, small=True, names=[NAME, TEST_NAME], features=TINY, progress=False)
    assert sorted(again["run"]["built"]) == sorted([NAME, TEST_NAME]) and not again["run"]["failed"]
    assert again["encoder"] == "tiny-colour" and again["train"] == [f"bundles/{NAME}"]
    for n in (NAME, TEST_NAME):
        assert read_metadata(out / "bundles" / n).features["encoder"] == "tiny-colour"
        load_bundle(out / "bundles" / n)  # every file, the linked pixels included, matches its checksum
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob(".*lock"))


def test_a_rerun_resumes_finished_bundles_without_touching_them(built, tmp_path):
    """The on-disk format is unchanged: a rerun of the same command reuses a finished bundle (same files,
    same inodes) and its record."""
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = _copy(built, tmp_path)
    bundle = out / "bundles" / NAME
    inodes = {p.name: p.stat().st_ino for p in bundle.iterdir()}
    before = _state(out)
    again = make_c16_dataset(out, small=True, names=[NAME, TEST_NAME], progress=False)
    assert sorted(again["run"]["resumed"]) == sorted([NAME, TEST_NAME]) and not again["run"]["built"]
    assert {p.name: p.stat().st_ino for p in bundle.iterdir()} == inodes and _state(out) == before
