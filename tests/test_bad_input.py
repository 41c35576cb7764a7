"""Bad-input classes not covered elsewhere: unknown TIFF compression, duplicate vertex Order."""
from __future__ import annotations

import numpy as np
import pytest
import tifffile

from data_tools.annotations import load_annotations
from data_tools.errors import SlideError
from data_tools.slides import open_slide


def test_unknown_compression_is_a_slide_error(tmp_path):
    path = tmp_path / "odd.tif"
    tifffile.imwrite(path, np.zeros((64, 64, 3), np.uint8), tile=(32, 32), compression="zlib", photometric="rgb")
    with tifffile.TiffFile(path) as tif:
        offset = tif.pages[0].tags["Compression"].valueoffset
    data = bytearray(path.read_bytes())
    data[offset:offset + 2] = (65000).to_bytes(2, "little")  # no codec has this number
    path.write_bytes(bytes(data))
    with pytest.raises(SlideError, match="odd.tif"):
        with open_slide(path) as reader:
            reader.read_level(0)


def test_duplicate_order_values_warn_and_keep_file_order(tmp_path):
    xml = tmp_path / "dup.xml"
    coords = [(0, 0, 0), (1, 100, 0), (1, 100, 100), (2, 0, 100)]  # two vertices share Order 1
    xml.write_text('<ASAP_Annotations><Annotations><Annotation Name="a" Type="Polygon" PartOfGroup="_0">'
                   "<Coordinates>" + "".join(f'<Coordinate Order="{o}" X="{x}" Y="{y}"/>' for o, x, y in coords)
                   + "</Coordinates></Annotation></Annotations></ASAP_Annotations>")
    with pytest.warns(UserWarning, match="duplicate Order"):
        ann = load_annotations(xml)
    assert ann.tumour.area == pytest.approx(100 * 100)
