"""A dataset rerun decides "already done" by a slide's fingerprint: for a MIRAX slide that is every file of its data
folder (Slidedat.ini, Index.dat, Data*.dat), not only the .mrxs, so a slide whose pixels changed is rebuilt."""

from __future__ import annotations

import os

import numpy as np
import pytest

from data_tools.datasets.build import _fingerprint


def _slide(where, seed: int = 0):
    from mirax_fixture import mirax

    rng = np.random.default_rng(seed)
    return mirax(where, rng.integers(0, 255, (256, 256, 3), np.uint8))[0]


@pytest.mark.parametrize("name", ["Data0000.dat", "Index.dat", "Slidedat.ini"])
def test_a_changed_file_of_the_data_folder_changes_the_fingerprint(tmp_path, name):
    path = _slide(tmp_path / "S" / "slide.mrxs")
    before = _fingerprint(path)
    f = path.with_suffix("") / name
    st = f.stat()
    f.write_bytes(f.read_bytes() + b"\0")  # one byte more ...
    assert _fingerprint(path) != before
    f.write_bytes(f.read_bytes()[:-1])  # ... or the same size, written later
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    assert _fingerprint(path) != before
    assert _fingerprint(path.with_suffix(".tif")) == {"bytes": 0, "mtime_ns": 0}  # a missing file: as before


def test_a_single_file_slide_is_fingerprinted_as_before(tmp_path):
    f = tmp_path / "a.tif"
    f.write_bytes(b"x" * 10)
    assert _fingerprint(f) == {"bytes": 10, "mtime_ns": f.stat().st_mtime_ns}


def test_a_dataset_rebuilds_a_mirax_slide_whose_data_file_changed(tmp_path):
    pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")
    from data_tools.datasets.build import build_dataset

    slides = tmp_path / "slides"
    a, b = _slide(slides / "a.mrxs", 0), _slide(slides / "b.mrxs", 1)
    out = tmp_path / "ds"
    first = build_dataset(slides, out, levels=(2, 3), tile_size=64, test_fraction=0, progress=False)
    assert not first["failed"] and sorted(first["built"]) == ["a", "b"]
    again = build_dataset(slides, out, levels=(2, 3), tile_size=64, test_fraction=0, progress=False)
    assert sorted(again["resumed"]) == ["a", "b"]
    # a's camera images replaced by b's (its Index.dat too): a's pixels changed, its .mrxs did not
    for name in ("Data0000.dat", "Index.dat"):
        (a.with_suffix("") / name).write_bytes((b.with_suffix("") / name).read_bytes())
    third = build_dataset(slides, out, levels=(2, 3), tile_size=64, test_fraction=0, progress=False)
    assert third["built"] == ["a"] and third["resumed"] == ["b"], third
