"""Bad-input classes not covered elsewhere: unknown TIFF compression, duplicate vertex Order."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from data_tools.annotations import load_annotations
from data_tools.errors import SlideError
from data_tools.slide_files.open import open_slide


def test_unknown_compression_is_a_slide_error(tmp_path):
    path = tmp_path / "odd.tif"
    tifffile.imwrite(path, np.zeros((64, 64, 3), np.uint8), tile=(32, 32), compression="zlib", photometric="rgb")
    with tifffile.TiffFile(path) as tif:
        offset = tif.pages[0].tags["Compression"].valueoffset
    data = bytearray(path.read_bytes())
    data[offset : offset + 2] = (65000).to_bytes(2, "little")  # no codec has this number
    path.write_bytes(bytes(data))
    with pytest.raises(SlideError, match="odd.tif"):
        with open_slide(path) as reader:
            reader.read_level(0)


def test_duplicate_order_values_warn_and_keep_file_order(tmp_path):
    xml = tmp_path / "dup.xml"
    coords = [(0, 0, 0), (1, 100, 0), (1, 100, 100), (2, 0, 100)]  # two vertices share Order 1
    xml.write_text(
        '<ASAP_Annotations><Annotations><Annotation Name="a" Type="Polygon" PartOfGroup="_0">'
        "<Coordinates>"
        + "".join(f'<Coordinate Order="{o}" X="{x}" Y="{y}"/>' for o, x, y in coords)
        + "</Coordinates></Annotation></Annotations></ASAP_Annotations>"
    )
    with pytest.warns(UserWarning, match="duplicate Order"):
        ann = load_annotations(xml)
    assert ann.tumour.area == pytest.approx(100 * 100)


@pytest.mark.parametrize("second", [(96, 96), (64, 20)])  # larger than level 0; wrong aspect ratio
def test_inconsistent_sub_levels_are_left_out(tmp_path, second):
    """tifffile leaves inconsistent sub-resolution levels out of the pyramid: the slide reads as
    its valid levels (the bundle builder then makes the coarser levels itself)."""
    path = tmp_path / "pyramid.tif"
    with tifffile.TiffWriter(path) as tif:
        tif.write(np.zeros((64, 64, 3), np.uint8), tile=(16, 16), photometric="rgb", subifds=1)
        tif.write(np.zeros((*second[::-1], 3), np.uint8), tile=(16, 16), photometric="rgb", subfiletype=1)
    with open_slide(path) as reader:
        assert [(lv.width, lv.height) for lv in reader.levels] == [(64, 64)]


@pytest.mark.parametrize("sizes", [[(64, 64), (96, 96)], [(64, 64), (64, 64)], [(64, 64), (32, 10)]])
def test_inconsistent_level_lists_are_refused(sizes):
    """Our own guard, for readers that do list such levels: larger, equal or distorted levels."""
    from data_tools.slide_files.base import LevelInfo, check_levels

    levels = [LevelInfo(w, h, 64 / w, None, "NONE") for w, h in sizes]
    with pytest.raises(SlideError, match="inconsistent pyramid"):
        check_levels("odd.tif", levels)
