"""A MIRAX slide's data folder is checked entry by entry (lstat only) before anything opens it: a FIFO, a device or a
link leading outside the folder is refused in one line at once (no open blocks on a FIFO), a name Slidedat.ini gives
that leads outside the folder is refused, and the child process OpenSlide first opens a slide in has a short time
limit that its message states."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from data_tools.errors import SlideError
from data_tools.slide_files.mirax import check_mirax, slide_files

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs need a POSIX system")


@pytest.fixture(scope="module")
def good_slide(tmp_path_factory):
    """A 256 × 256 px MIRAX slide (two levels, PNG camera images), written by tests/mirax_fixture.py."""
    from mirax_fixture import mirax

    rng = np.random.default_rng(0)
    return mirax(tmp_path_factory.mktemp("mirax") / "slide.mrxs", rng.integers(0, 255, (256, 256, 3), np.uint8))[0]


def _copy(good: Path, where: Path) -> Path:
    shutil.copytree(good.with_suffix(""), where / "S")
    (where / "S.mrxs").write_bytes(b"")
    return where / "S.mrxs"


@pytest.mark.parametrize("name", ["Index.dat", "Data0000.dat", "Slidedat.ini", "Extra.dat"])
def test_a_fifo_in_the_data_folder_is_refused_at_once(good_slide, tmp_path, name):
    path = _copy(good_slide, tmp_path)
    (path.with_suffix("") / name).unlink(missing_ok=True)
    os.mkfifo(path.with_suffix("") / name)
    start = time.perf_counter()
    with pytest.raises(SlideError, match=rf"S\.mrxs: S/{name} in its data folder is a FIFO, not a regular file") as e:
        check_mirax(path)
    assert time.perf_counter() - start < 5.0  # not the child process's time limit: nothing was opened
    assert "\n" not in str(e.value)


def test_a_link_leading_outside_the_data_folder_is_refused(good_slide, tmp_path):
    path = _copy(good_slide, tmp_path)
    outside = tmp_path / "elsewhere.dat"
    shutil.move(path.with_suffix("") / "Data0000.dat", outside)
    (path.with_suffix("") / "Data0000.dat").symlink_to(outside)
    with pytest.raises(SlideError, match=r"S/Data0000\.dat in its data folder is a symbolic link leading outside"):
        check_mirax(path)


def test_a_link_to_a_fifo_inside_the_folder_is_refused_and_a_link_to_a_file_inside_is_read(good_slide, tmp_path):
    path = _copy(good_slide, tmp_path)
    folder = path.with_suffix("")
    shutil.move(folder / "Data0000.dat", folder / "real.dat")
    (folder / "Data0000.dat").symlink_to("real.dat")
    check_mirax(path)  # a link to a regular file of the folder: fine
    os.mkfifo(folder / "pipe")
    (folder / "Index2.dat").symlink_to("pipe")
    with pytest.raises(SlideError, match=r"S/[A-Za-z0-9]+(\.dat)? in its data folder is .*FIFO"):
        check_mirax(path)


@pytest.mark.parametrize("key, value", [("FILE_0", "../../outside.dat"), ("INDEXFILE", "/etc/passwd")])
def test_a_named_file_outside_the_data_folder_is_refused(good_slide, tmp_path, key, value):
    path = _copy(good_slide, tmp_path)
    ini = path.with_suffix("") / "Slidedat.ini"
    text = ini.read_text()
    old = {"FILE_0": "FILE_0=Data0000.dat", "INDEXFILE": "INDEXFILE=Index.dat"}[key]
    ini.write_text(text.replace(old, f"{key}={value}"))
    with pytest.raises(SlideError, match=rf"its Slidedat.ini names {key}=.*not a file name inside its data folder"):
        check_mirax(path)


def test_the_good_slide_passes_and_lists_every_file(good_slide):
    check_mirax(good_slide)
    names = [p.name for p in slide_files(good_slide)]
    assert names == ["slide.mrxs", "Data0000.dat", "Index.dat", "Slidedat.ini"]


def test_the_child_process_time_limit_is_short_and_named_when_it_fires(good_slide, monkeypatch):
    pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")
    from data_tools.slide_files import openslide as reader

    assert reader.PROBE_TIMEOUT_S <= 60
    monkeypatch.setattr(reader, "PROBE_TIMEOUT_S", 1)
    monkeypatch.setattr(reader, "_PROBE_CODE", "import time; time.sleep(30)")
    monkeypatch.setattr(reader, "_probed", {})
    start = time.perf_counter()
    with pytest.raises(SlideError, match=r"did not open it within the 1 s time limit of the separate process") as e:
        reader._probe(os.fspath(good_slide))
    assert time.perf_counter() - start < 10.0 and "\n" not in str(e.value)
