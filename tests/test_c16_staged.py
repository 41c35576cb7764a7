"""Issue 30 on the C16 path: ``python -m data_tools c16`` builds each bundle into a hidden
``bundles/.NAME.tmp-*`` and swaps it in once whole, so a failed rebuild (the disk full while the bundle is
written, or while a feature grid is added to a built set) leaves the previous bundle and its record as they
were, and the next run rebuilds it. One slide of the ``--small`` set (a normal slide: its own tissue, seconds
to build); features from the tiny test encoder of tests/encoder_helpers.py."""
from __future__ import annotations

import errno
import json
from pathlib import Path

import numpy as np
import pytest

from data_tools.bundle_format import load_bundle, read_metadata

NAME = "Normal_042"  # one slide of SMALL_SLIDES
TINY = "encoder_helpers:tiny_colour"


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    from data_tools.datasets.c16 import make_c16_dataset

    out = tmp_path_factory.mktemp("c16staged") / "c16"
    make_c16_dataset(out, small=True, names=[NAME], progress=False)
    return out


def _copy(built: Path, tmp_path: Path) -> Path:
    import shutil

    return Path(shutil.copytree(built, tmp_path / "c16"))


def _state(out: Path) -> tuple[dict, bytes]:
    """Every file of the slide's bundle (name -> bytes) and its record's bytes."""
    bundle = out / "bundles" / NAME
    files = {p.name: p.read_bytes() for p in sorted(bundle.iterdir()) if p.is_file()}
    return files, (out / "records" / f"{NAME}.json").read_bytes()


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


def _check_kept(out: Path, before: tuple[dict, bytes], result: dict) -> None:
    bundle = out / "bundles" / NAME
    assert _state(out) == before  # before: the bundle removed and its record deleted
    load_bundle(bundle)           # whole and verified
    assert result["run"]["kept"] == [NAME] and list(result["run"]["failed"]) == [NAME]
    reason = result["run"]["failed"][NAME]
    assert f"bundles/{NAME}" in reason and "No space left on device" in reason and ".tmp-" not in reason
    failure = json.loads((out / "records" / "failed" / f"{NAME}.json").read_text())
    assert failure["previous_kept"] is True and failure["reason"] == reason
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob(".*lock"))  # nothing half-written left


def test_a_failed_rebuild_keeps_the_previous_bundle_and_its_record(built, tmp_path, monkeypatch):
    """Another seed remakes the slide, so its bundle is written again; the disk fills after the bundle
    writer's first file. Then, the disk freed, a rerun builds and swaps in the new bundle."""
    from data_tools.datasets.c16 import make_c16_dataset

    out = _copy(built, tmp_path)
    before = _state(out)
    calls = _full_disk_after_first(monkeypatch, np, "save", inside="/bundles/")
    result = make_c16_dataset(out, small=True, names=[NAME], seed=1, progress=False)
    assert len(calls) == 2  # the writer wrote one file into the staged bundle, then the disk was full
    _check_kept(out, before, result)

    monkeypatch.undo()
    again = make_c16_dataset(out, small=True, names=[NAME], seed=1, progress=False)
    assert again["run"]["built"] == [NAME] and not again["run"]["failed"]
    assert json.loads((out / "records" / f"{NAME}.json").read_text())["settings"]["seed"] == 1
    assert read_metadata(out / "bundles" / NAME)["metadata_sha256"] != json.loads(before[0]["metadata.json"])[
        "metadata_sha256"]
    assert not (out / "records" / "failed" / f"{NAME}.json").exists()
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob(".*lock"))


def test_adding_features_that_fail_leaves_the_pixel_bundle_untouched(built, tmp_path, monkeypatch):
    """A built set given ``--features``: the up-to-date bundle is hard-linked into the staged folder and the
    grid computed there; the disk fills after the first feature chunk. The old bundle's files (the very
    inodes the staged folder shared) are unchanged, and the rerun adds the grid, the old files still whole."""
    import data_tools.features.grid as grid
    from data_tools.datasets.c16 import make_c16_dataset

    out = _copy(built, tmp_path)
    before = _state(out)
    calls = _full_disk_after_first(monkeypatch, grid, "save_array", inside="/bundles/")
    result = make_c16_dataset(out, small=True, names=[NAME], features=TINY, progress=False)
    assert len(calls) == 2
    _check_kept(out, before, result)
    assert read_metadata(out / "bundles" / NAME).features is None

    monkeypatch.undo()
    again = make_c16_dataset(out, small=True, names=[NAME], features=TINY, progress=False)
    assert again["run"]["built"] == [NAME] and not again["run"]["failed"]
    meta = read_metadata(out / "bundles" / NAME)
    assert meta.features["encoder"] == "tiny-colour"
    load_bundle(out / "bundles" / NAME)  # every file, the linked pixels included, matches its checksum
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob(".*lock"))


def test_a_rerun_resumes_finished_bundles_without_touching_them(built, tmp_path):
    """The on-disk format is unchanged: a rerun of the same command reuses a finished bundle (same files,
    same inodes) and its record."""
    from data_tools.datasets.c16 import make_c16_dataset

    out = _copy(built, tmp_path)
    bundle = out / "bundles" / NAME
    inodes = {p.name: p.stat().st_ino for p in bundle.iterdir()}
    before = _state(out)
    again = make_c16_dataset(out, small=True, names=[NAME], progress=False)
    assert again["run"]["resumed"] == [NAME] and not again["run"]["built"]
    assert {p.name: p.stat().st_ino for p in bundle.iterdir()} == inodes and _state(out) == before
