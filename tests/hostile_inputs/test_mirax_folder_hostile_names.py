"""A hostile pass over a MIRAX slide's data folder checks (:func:`data_tools.slide_files.mirax.check_mirax_files`):
an indented line of ``Slidedat.ini`` (a group or a key to GLib, a continuation of the previous value to
configparser) hiding a name outside the folder or a size from the check; a FIFO whose name holds a newline (the
refusal stays one line); thousands of entries; a name with a newline; a file named twice; ``Index.dat`` a hard link
to a file outside the folder (read, never written)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from data_tools.errors import SlideError
from data_tools.slide_files.mirax import check_mirax, slide_files

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs need a POSIX system")


@pytest.fixture(scope="module")
def good_slide(tmp_path_factory):
    from mirax_fixture import mirax

    rng = np.random.default_rng(0)
    return mirax(tmp_path_factory.mktemp("mirax") / "slide.mrxs", rng.integers(0, 255, (256, 256, 3), np.uint8))[0]


def _copy(good: Path, where: Path) -> Path:
    shutil.copytree(good.with_suffix(""), where / "S")
    (where / "S.mrxs").write_bytes(b"")
    return where / "S.mrxs"


def _edit_ini(path: Path, old: str, new: str, extra: str = "") -> None:
    ini = path.with_suffix("") / "Slidedat.ini"
    text = ini.read_text()
    assert old in text
    ini.write_text(text.replace(old, new) + extra)


def _opens(path: Path) -> None:
    pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")
    from data_tools.slide_files.open import open_slide

    reader = open_slide(path)
    getattr(reader, "close", lambda: None)()


@pytest.mark.parametrize("indent", ["  ", "\t", " \t\f"])
def test_an_indented_group_hiding_an_index_file_outside_the_folder_is_refused(good_slide, tmp_path, indent):
    """Was: passed the check (configparser read ``  [HIERARCHICAL]`` as a continuation of ``[X]``'s ``A``, so its
    ``INDEXFILE`` was never seen) and OpenSlide opened ``../../outside/Index.dat``, a file outside the folder."""
    path = _copy(good_slide, tmp_path)
    (tmp_path / "outside").mkdir()
    shutil.move(path.with_suffix("") / "Index.dat", tmp_path / "outside" / "Index.dat")
    hidden = f"\n[X]\nA=1\n{indent}[HIERARCHICAL]\nINDEXFILE=../../outside/Index.dat\n"
    _edit_ini(path, "INDEXFILE=Index.dat", "INDEXFILE=Index2.dat", hidden)
    with pytest.raises(SlideError, match=r"names INDEXFILE='\.\./\.\./outside/Index\.dat': not a file name inside"):
        check_mirax(path)


def test_an_indented_key_hiding_a_size_past_the_limits_is_refused(good_slide, tmp_path):
    """Was: ``  IMAGENUMBER_X=2000000000`` a continuation of the previous value, unseen by the size check; GLib
    reads it (and OpenSlide's 32-bit sizes overflow)."""
    path = _copy(good_slide, tmp_path)
    ini = (path.with_suffix("") / "Slidedat.ini").read_text()
    line = next(x for x in ini.splitlines() if x.startswith("IMAGENUMBER_X="))
    _edit_ini(path, line, line + "\n  IMAGENUMBER_X=2000000000")
    with pytest.raises(SlideError, match=r"S\.mrxs: ") as e:
        check_mirax(path)
    assert "2000000000" in str(e.value) or "2,000,000,000" in str(e.value)


def test_a_fifo_whose_name_holds_a_newline_is_refused_in_one_line(good_slide, tmp_path):
    """Was: the refusal quoted the name as it is, its newline splitting the line in two."""
    path = _copy(good_slide, tmp_path)
    os.mkfifo(path.with_suffix("") / "evil\nname")
    with pytest.raises(SlideError, match=r"'S/evil\\nname' in its data folder is a FIFO") as e:
        check_mirax(path)
    assert "\n" not in str(e.value)


def test_thousands_of_entries_and_names_with_newlines_pass_and_are_fingerprinted(good_slide, tmp_path):
    path = _copy(good_slide, tmp_path)
    folder = path.with_suffix("")
    for i in range(3000):
        (folder / f"notes-{i}.txt").write_bytes(b"")
    (folder / "Data\n0000.dat").write_bytes(b"not read")  # a name with a newline: a file OpenSlide never names
    check_mirax(path)
    files = slide_files(path)
    assert len(files) == 1 + 3 + 3001 and folder / "Data\n0000.dat" in files
    _opens(path)


def test_a_data_file_named_twice_opens_and_an_index_named_as_the_data_file_is_one_line(good_slide, tmp_path):
    (tmp_path / "a").mkdir()
    path = _copy(good_slide, tmp_path / "a")
    _edit_ini(path, "FILE_COUNT=1", "FILE_COUNT=2")
    _edit_ini(path, "FILE_0=Data0000.dat", "FILE_0=Data0000.dat\nFILE_1=Data0000.dat")
    check_mirax(path)
    _opens(path)  # two entries reading one file: OpenSlide reads it twice, nothing worse
    (tmp_path / "b").mkdir()
    path = _copy(good_slide, tmp_path / "b")
    _edit_ini(path, "INDEXFILE=Index.dat", "INDEXFILE=Data0000.dat")
    pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")
    with pytest.raises(SlideError, match=r"S\.mrxs: format not recognised or file corrupt") as e:
        _opens(path)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("content", ["garbage", "the slide's own"])
def test_an_index_dat_hard_linked_to_a_file_outside_is_read_never_written(good_slide, tmp_path, content):
    """A hard link is a regular file: nothing can tell it leads outside. It is read like any Index.dat (garbage: one
    line; the real index: the slide opens), and the file outside is left as it was."""
    pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")
    path = _copy(good_slide, tmp_path)
    outside = tmp_path / "outside.bin"
    if content == "garbage":
        outside.write_bytes(b"garbage" * 100)
    else:
        shutil.copy(path.with_suffix("") / "Index.dat", outside)
    (path.with_suffix("") / "Index.dat").unlink()
    os.link(outside, path.with_suffix("") / "Index.dat")
    before = (outside.read_bytes(), outside.stat().st_mtime_ns)
    if content == "garbage":
        with pytest.raises(SlideError, match=r"S\.mrxs: format not recognised or file corrupt"):
            _opens(path)
    else:
        _opens(path)
    assert (outside.read_bytes(), outside.stat().st_mtime_ns) == before
