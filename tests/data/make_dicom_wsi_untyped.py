"""Write ``tests/data/dicom-wsi-untyped/slide.dcm``: a DICOM WSI with the traits of a real file that
neither OpenSlide nor wsidicom reads, derived from ``tests/data/dicom-wsi/level0.dcm`` with pydicom.

Run from the repository root: ``python tests/data/make_dicom_wsi_untyped.py``. The traits:

* no ``ImageType`` (nor the frame type in the shared functional groups);
* 65-character UIDs (Study, Series, SOP Instance, Frame of Reference; the standard allows 64);
* ``TILED_SPARSE`` with 3 of the 20 frames left out (the tiles at (column, row) (0, 0), (3, 2) and
  (1, 4)): a reader must place the 17 others by their Per-frame Functional Groups' plane positions
  and paint the absent ones as background.

The frames are the source's JPEG frames, copied byte for byte (not re-encoded), so the pixels of a
stored tile equal those of ``level0.dcm`` decoded. Deterministic.
"""

from __future__ import annotations

import sys
from pathlib import Path

from pydicom import dcmread
from pydicom.encaps import encapsulate, generate_frames
from pydicom.sequence import Sequence

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "dicom-wsi" / "level0.dcm"
OUT = HERE / "dicom-wsi-untyped" / "slide.dcm"
ABSENT = {(0, 0), (3, 2), (1, 4)}  # (column, row) of the tiles left out
TILE = 128


def _long_uid(uid: str) -> str:
    """``uid`` padded with digits to 65 characters (one over the standard's 64)."""
    return uid + "." + "1" * (64 - len(uid))


def main() -> int:
    ds = dcmread(SOURCE)
    frames = list(generate_frames(ds.PixelData, number_of_frames=int(ds.NumberOfFrames)))
    keep, items = [], []
    for frame, item in zip(frames, ds.PerFrameFunctionalGroupsSequence):
        pos = item.PlanePositionSlideSequence[0]
        tile = (
            (int(pos.ColumnPositionInTotalImagePixelMatrix) - 1) // TILE,
            (int(pos.RowPositionInTotalImagePixelMatrix) - 1) // TILE,
        )
        if tile not in ABSENT:
            keep.append(frame)
            items.append(item)
    del ds.ImageType
    del ds.SharedFunctionalGroupsSequence[0].WholeSlideMicroscopyImageFrameTypeSequence
    for key in ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID", "FrameOfReferenceUID"):
        setattr(ds, key, _long_uid(str(getattr(ds, key))))
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    ds.PerFrameFunctionalGroupsSequence = Sequence(items)
    ds.NumberOfFrames = len(keep)
    ds.PixelData = encapsulate(keep, has_bot=True)
    ds["PixelData"].VR = "OB"
    OUT.parent.mkdir(exist_ok=True)
    ds.save_as(OUT, enforce_file_format=True)
    print(f"wrote {OUT}: {len(keep)} of {len(frames)} frames, {OUT.stat().st_size / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
