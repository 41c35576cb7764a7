"""One regular-file guard for every reader of a user's files: bundles (data_tools.bundle_files.safe_files.own_file) and slide
head folders (histojax.reading.heads.files.read_regular) both use data_tools.bundle_files.safe_files.not_regular /
open_regular (the lower floor), so a link, a FIFO or a folder is refused alike, in one line naming the file."""

from __future__ import annotations

import os

import pytest

from data_tools.bundle_files import safe_files
from data_tools.errors import BundleError
from histojax.reading.heads import files

posix_only = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs need a POSIX file system")


def test_heads_read_through_the_bundles_guard():
    assert files.not_regular is safe_files.not_regular and files.open_regular is safe_files.open_regular


@posix_only
def test_not_regular_names_what_the_entry_is(tmp_path):
    (tmp_path / "f").write_bytes(b"x")
    os.symlink(tmp_path / "f", tmp_path / "l")
    os.mkfifo(tmp_path / "p")
    (tmp_path / "d").mkdir()
    kinds = {n: safe_files.not_regular(os.lstat(tmp_path / n)) for n in ("f", "l", "p", "d")}
    assert kinds == {"f": None, "l": "a symbolic link", "p": "a FIFO", "d": "a folder"}


@posix_only
def test_a_fifo_is_refused_by_both_readers_without_blocking(tmp_path):
    os.mkfifo(tmp_path / "config.json")
    with pytest.raises(files.HeadFileError, match="not a regular file") as e:
        files.read_config(tmp_path / "config.json")
    assert len(str(e.value).splitlines()) == 1 and str(tmp_path / "config.json") in str(e.value)
    with pytest.raises(BundleError, match="not a regular file"):
        safe_files.own_file(tmp_path, "config.json")


def test_open_regular_refuses_a_file_swapped_after_the_check(tmp_path):
    (tmp_path / "a").write_bytes(b"a")
    (tmp_path / "b").write_bytes(b"b")
    st = os.lstat(tmp_path / "a")
    os.replace(tmp_path / "b", tmp_path / "a")  # another inode now stands at the checked path
    with pytest.raises(safe_files.ChangedFileError):
        safe_files.open_regular(tmp_path / "a", st)
    with safe_files.open_regular(tmp_path / "a", os.lstat(tmp_path / "a")) as f:
        assert f.read() == b"b"


# ----------------------------------------------------------------------------- one slide loader
def test_both_head_fits_read_a_bundle_through_one_loader(tmp_path):
    """slides.load_slide and learned_head_fit.load_views share slides.read_bundle (read, verify, feature levels)
    and slides.finest_views (view -> feature cell, tissue views): the same views and vectors."""
    import numpy as np
    from learned_fixture import make_cohort

    from baselines.reading import learned_head_fit, slides

    assert learned_head_fit.read_bundle is slides.read_bundle
    assert learned_head_fit.finest_views is slides.finest_views
    c = make_cohort(tmp_path / "ds", tumour=1, normal=1, test_tumour=0, test_normal=0, dim=8)
    bundle = c["root"] / "bundles" / c["names"]["train"][0]
    grid = slides.load_slide(bundle, dim=0, grid=True)
    views = learned_head_fit.load_views(bundle)
    ys, xs = views["yx"].T
    assert grid["tissue"].sum() == len(views["features"]) and grid["tissue"][ys, xs].all()
    np.testing.assert_array_equal(grid["features"][ys, xs], views["features"])
