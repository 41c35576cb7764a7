"""The folder of slides given to ``histojax dataset`` that is a file is called a file, not "no such folder"."""

from __future__ import annotations

import pytest


def test_a_file_given_as_the_folder_of_slides_is_called_a_file(tmp_path):
    """Was: ``histojax dataset FILE --out DIR`` said "no such folder of slides" of a file that is there."""
    from data_tools.datasets.discover import discover
    from data_tools.errors import HistojaxDataError

    (tmp_path / "slide.txt").write_text("hi")
    with pytest.raises(HistojaxDataError, match="slide.txt: a file, not a folder of slides"):
        discover(tmp_path / "slide.txt")
    with pytest.raises(HistojaxDataError, match="nope: no such folder of slides"):
        discover(tmp_path / "nope")
