"""Write a tiny valid 3DHISTECH MIRAX slide (``.mrxs`` + its data folder) for tests/data_pipeline/test_openslide.py, following
OpenSlide's MIRAX reader (src/openslide-vendor-mirax.c: Slidedat.ini keys, Index.dat layout) and its format notes.

The slide: ``IMAGENUMBER_X`` × ``IMAGENUMBER_Y`` camera images of ``tile`` px (one per camera position:
``CameraImageDivisionsPerSide=1``, no overlap, so no position buffer is needed and OpenSlide lays them edge to
edge), PNG-encoded (lossless, so the pixels read back are the ones written), two zoom levels (level 1 = level 0
averaged 2 × 2, ``IMAGE_CONCAT_FACTOR=1``: one image per 2 × 2 of level 0), every image in ``Data0000.dat``.

``Index.dat``: ``"01.02"`` + the slide id; at that offset the hierarchical root pointer (→ a table of one pointer
per zoom level) and the non-hierarchical root (0: no records); each level pointer → ``(0, page)``, the page
``(count, next = 0)`` then ``count`` records ``(image index = y · IMAGENUMBER_X + x, offset, length, file 0)``.
"""

from __future__ import annotations

import io
import struct
from pathlib import Path

import numpy as np
from PIL import Image


def mirax(path, rgb: np.ndarray, tile: int = 128, mpp: float = 0.25):
    """Write ``rgb`` ``(H, W, 3)`` uint8 (H, W multiples of ``2 · tile``) as the MIRAX slide ``path`` (``.mrxs``;
    the data folder beside it); ``mpp`` µm/px at level 0. Returns ``(path, [(level pixels, concat), ...])``."""
    path = Path(path)
    data_dir = path.with_suffix("")
    data_dir.mkdir(parents=True)
    h, w = rgb.shape[:2]
    nx, ny = w // tile, h // tile
    slide_id = "histojax-mirax-fixture-0001"
    half = rgb.reshape(h // 2, 2, w // 2, 2, 3).mean((1, 3)).round().astype(np.uint8)
    levels = [(rgb, 1), (half, 2)]
    blob = io.BytesIO()
    entries = []
    for k, (img, concat) in enumerate(levels):
        ents = []
        for y in range(0, ny, concat):
            for x in range(0, nx, concat):
                t = img[y // concat * tile : (y // concat + 1) * tile, x // concat * tile : (x // concat + 1) * tile]
                buf = io.BytesIO()
                Image.fromarray(np.ascontiguousarray(t)).save(buf, "PNG")
                ents.append((y * nx + x, blob.tell(), len(buf.getvalue()), 0))
                blob.write(buf.getvalue())
        entries.append(ents)
    (data_dir / "Data0000.dat").write_bytes(blob.getvalue())
    head = b"01.02" + slide_id.encode()
    out = bytearray(head)
    hier_root = len(out)
    out += b"\0" * 8  # hier pointer, nonhier pointer
    table = len(out)
    out += b"\0" * (4 * len(levels))
    struct.pack_into("<i", out, hier_root, table)
    struct.pack_into("<i", out, hier_root + 4, 0)
    for k, ents in enumerate(entries):
        hdr = len(out)
        out += struct.pack("<ii", 0, hdr + 8)
        out += struct.pack("<ii", len(ents), 0)
        for e in ents:
            out += struct.pack("<iiii", *e)
        struct.pack_into("<i", out, table + 4 * k, hdr)
    (data_dir / "Index.dat").write_bytes(bytes(out))
    sections = "".join(
        f"""
[LAYER_0_LEVEL_{k}_SECTION]
IMAGE_CONCAT_FACTOR={k}
OVERLAP_X=0
OVERLAP_Y=0
MICROMETER_PER_PIXEL_X={mpp * 2**k}
MICROMETER_PER_PIXEL_Y={mpp * 2**k}
IMAGE_FILL_COLOR_BGR=16777215
DIGITIZER_WIDTH={tile}
DIGITIZER_HEIGHT={tile}
IMAGE_FORMAT=PNG
"""
        for k in range(len(levels))
    )
    (data_dir / "Slidedat.ini").write_text(
        f"""[GENERAL]
SLIDE_VERSION=01.02
SLIDE_ID={slide_id}
IMAGENUMBER_X={nx}
IMAGENUMBER_Y={ny}
OBJECTIVE_MAGNIFICATION=20
CameraImageDivisionsPerSide=1

[HIERARCHICAL]
HIER_COUNT=1
NONHIER_COUNT=0
INDEXFILE=Index.dat
HIER_0_NAME=Slide zoom level
HIER_0_COUNT={len(levels)}
"""
        + "".join(
            f"HIER_0_VAL_{k}=ZoomLevel_{k}\nHIER_0_VAL_{k}_SECTION=LAYER_0_LEVEL_{k}_SECTION\n"
            for k in range(len(levels))
        )
        + """
[DATAFILE]
FILE_COUNT=1
FILE_0=Data0000.dat
"""
        + sections
    )
    path.write_bytes(b"")  # the .mrxs itself: OpenSlide needs it to exist
    return path, levels
