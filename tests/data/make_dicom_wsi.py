"""Write the small DICOM WSI fixture ``tests/data/dicom-wsi/`` from real pixels.

Run from the repository root: ``python tests/data/make_dicom_wsi.py`` (needs the ``dicom`` extra).

The pixels are a 2048×2560 px crop of ``histojax/data/CMU-1-Small-Region.svs`` (CC0) at downsample 4,
so the fixture's level 0 is 512×640 px at ~2 µm/px. Three VL Whole Slide Microscopy instances make one
pyramid, each exercising something real DICOM WSI files do:

* ``level0.dcm``: 512×640 px, JPEG baseline (YBR_FULL_422) frames of 128×128, ``TILED_SPARSE`` with the
  20 frames stored **column by column** (not row-major), positions in the Per-frame Functional Groups;
* ``level1.dcm``: 256×320 px, **JPEG 2000** frames, ``TILED_SPARSE`` row-major with **two frames
  absent** (the top-left and bottom-right tiles: a reader must paint them as background);
* ``level2.dcm``: 128×160 px, JPEG baseline, ``TILED_FULL`` (implicit row-major positions).

:func:`reference_levels` recomputes the pixels each level was encoded from (the absent tiles of level 1
painted white), so a test can check a reader puts every frame where its position says. Deterministic:
fixed UIDs, no dates.
"""

from __future__ import annotations

import sys
from pathlib import Path

import imagecodecs
import numpy as np
from PIL import Image
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.encaps import encapsulate
from pydicom.sequence import Sequence
from pydicom.uid import JPEG2000, JPEGBaseline8Bit

ROOT = Path(__file__).resolve().parents[2]
SOURCE = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"
OUT = Path(__file__).resolve().parent / "dicom-wsi"
TILE = 128
DOWNSAMPLE = 4
CROP = (64, 160, 64 + 2048, 160 + 2560)  # level-0 px of the SVS: x0, y0, x1, y1
UID_ROOT = "1.2.826.0.1.3680043.10.1234.17."  # fixed, so the fixture is reproducible
WSI_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.77.1.6"


def _uid(suffix: str) -> str:
    return UID_ROOT + suffix


def _code(value: str, scheme: str, meaning: str) -> Dataset:
    item = Dataset()
    item.CodeValue, item.CodingSchemeDesignator, item.CodeMeaning = value, scheme, meaning
    return item


def _base_dataset(index: int, level: np.ndarray, mpp_um: float, syntax: str) -> Dataset:
    h, w = level.shape[:2]
    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = WSI_SOP_CLASS
    ds.file_meta.MediaStorageSOPInstanceUID = _uid(f"3.{index}")
    ds.file_meta.TransferSyntaxUID = syntax
    ds.file_meta.ImplementationClassUID = _uid("9")
    ds.SOPClassUID = WSI_SOP_CLASS
    ds.SOPInstanceUID = _uid(f"3.{index}")
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = _uid("1"), _uid("2"), _uid("4")
    ds.DimensionOrganizationUID = _uid("5")
    ds.Modality = "SM"
    ds.PatientName, ds.PatientID, ds.StudyID, ds.AccessionNumber = "CMU-1-Small-Region", "CMU-1", "1", ""
    ds.StudyDate = ds.StudyTime = ds.ContentDate = ds.ContentTime = ds.AcquisitionDateTime = ""
    ds.PatientBirthDate = ds.PatientSex = ds.ReferringPhysicianName = ""
    ds.SeriesNumber, ds.InstanceNumber = 1, index + 1
    ds.Manufacturer = "histojax test fixture"
    ds.ManufacturerModelName = ds.DeviceSerialNumber = ds.SoftwareVersions = "tests/data/make_dicom_wsi.py"
    ds.ImageType = (
        ["ORIGINAL", "PRIMARY", "VOLUME", "NONE"] if index == 0 else ["DERIVED", "PRIMARY", "VOLUME", "RESAMPLED"]
    )
    ds.BurnedInAnnotation = ds.SpecimenLabelInImage = "NO"
    ds.FocusMethod, ds.ExtendedDepthOfField = "AUTO", "NO"
    ds.VolumetricProperties = "VOLUME"
    ds.ContainerIdentifier = "CMU-1"
    ds.IssuerOfTheContainerIdentifierSequence = Sequence()
    ds.ContainerTypeCodeSequence = Sequence([_code("433466003", "SCT", "Microscope slide")])
    specimen = Dataset()
    specimen.SpecimenIdentifier, specimen.SpecimenUID = "CMU-1", _uid("6")
    specimen.IssuerOfTheSpecimenIdentifierSequence = Sequence()
    specimen.SpecimenPreparationSequence = Sequence()
    ds.SpecimenDescriptionSequence = Sequence([specimen])
    ds.PositionReferenceIndicator = "SLIDE_CORNER"
    ds.Rows = ds.Columns = TILE
    ds.TotalPixelMatrixColumns, ds.TotalPixelMatrixRows = w, h
    ds.TotalPixelMatrixFocalPlanes = ds.NumberOfOpticalPaths = 1
    spacing_mm = mpp_um * 1e-3 * (2**index)
    ds.ImagedVolumeWidth, ds.ImagedVolumeHeight, ds.ImagedVolumeDepth = w * spacing_mm, h * spacing_mm, 0.001
    origin = Dataset()
    origin.XOffsetInSlideCoordinateSystem, origin.YOffsetInSlideCoordinateSystem = 20.0, 40.0
    ds.TotalPixelMatrixOriginSequence = Sequence([origin])
    ds.ImageOrientationSlide = [0, -1, 0, -1, 0, 0]
    ds.SamplesPerPixel, ds.BitsAllocated, ds.BitsStored, ds.HighBit = 3, 8, 8, 7
    ds.PixelRepresentation, ds.PlanarConfiguration = 0, 0
    ds.PhotometricInterpretation = "YBR_FULL_422" if syntax == JPEGBaseline8Bit else "RGB"
    ds.LossyImageCompression = "01"
    ds.LossyImageCompressionRatio = 10.0
    ds.LossyImageCompressionMethod = "ISO_10918_1" if syntax == JPEGBaseline8Bit else "ISO_15444_1"
    measures = Dataset()
    measures.PixelSpacing = [spacing_mm, spacing_mm]
    measures.SliceThickness, measures.SpacingBetweenSlices = 0.001, 0.0
    shared = Dataset()
    shared.PixelMeasuresSequence = Sequence([measures])
    frame_type = Dataset()
    frame_type.FrameType = list(ds.ImageType)
    shared.WholeSlideMicroscopyImageFrameTypeSequence = Sequence([frame_type])
    shared_path = Dataset()
    shared_path.OpticalPathIdentifier = "0"
    shared.OpticalPathIdentificationSequence = Sequence([shared_path])
    ds.SharedFunctionalGroupsSequence = Sequence([shared])
    path = Dataset()
    path.OpticalPathIdentifier = "0"
    path.IlluminationTypeCodeSequence = Sequence([_code("111744", "DCM", "Brightfield illumination")])
    path.IlluminationColorCodeSequence = Sequence([_code("414298005", "SCT", "Full Spectrum")])
    ds.OpticalPathSequence = Sequence([path])
    return ds


def _frames(level: np.ndarray) -> dict[tuple[int, int], np.ndarray]:
    """Tiles of ``level`` keyed by (column, row) index, edge tiles padded with white to TILE×TILE."""
    h, w = level.shape[:2]
    tiles = {}
    for ty in range(-(-h // TILE)):
        for tx in range(-(-w // TILE)):
            tile = np.full((TILE, TILE, 3), 255, np.uint8)
            part = level[ty * TILE : (ty + 1) * TILE, tx * TILE : (tx + 1) * TILE]
            tile[: part.shape[0], : part.shape[1]] = part
            tiles[(tx, ty)] = tile
    return tiles


def _write(index: int, level: np.ndarray, mpp_um: float, syntax: str, order: list[tuple[int, int]] | None) -> None:
    """Write one instance; ``order`` lists the (column, row) tiles stored, in storage order
    (TILED_SPARSE), or ``None`` for TILED_FULL (all tiles, row-major)."""
    ds = _base_dataset(index, level, mpp_um, syntax)
    tiles = _frames(level)
    keys = sorted(tiles, key=lambda k: (k[1], k[0])) if order is None else order
    if syntax == JPEGBaseline8Bit:

        def encode(t):
            return imagecodecs.jpeg8_encode(t, level=90, colorspace="RGB", outcolorspace="YCBCR", subsampling="422")
    else:

        def encode(t):
            return imagecodecs.jpeg2k_encode(t, level=50, codecformat="J2K", colorspace="SRGB")

    ds.NumberOfFrames = len(keys)
    ds.DimensionOrganizationType = "TILED_FULL" if order is None else "TILED_SPARSE"
    if order is not None:
        per_frame = []
        spacing_mm = mpp_um * 1e-3 * (2**index)
        for tx, ty in keys:
            pos = Dataset()
            pos.ColumnPositionInTotalImagePixelMatrix = tx * TILE + 1  # 1-based
            pos.RowPositionInTotalImagePixelMatrix = ty * TILE + 1
            pos.XOffsetInSlideCoordinateSystem = 20.0 + ty * TILE * spacing_mm
            pos.YOffsetInSlideCoordinateSystem = 40.0 + tx * TILE * spacing_mm
            pos.ZOffsetInSlideCoordinateSystem = 0.0
            item = Dataset()
            item.PlanePositionSlideSequence = Sequence([pos])
            per_frame.append(item)
        ds.PerFrameFunctionalGroupsSequence = Sequence(per_frame)
    ds.PixelData = encapsulate([encode(tiles[k]) for k in keys], has_bot=True)
    ds["PixelData"].VR = "OB"
    ds.save_as(OUT / f"level{index}.dcm", enforce_file_format=True)


def _absent(level1_shape: tuple[int, ...]) -> set[tuple[int, int]]:
    """(column, row) of the tiles left out of level 1: the first and the last."""
    cols, rows = -(-level1_shape[1] // TILE), -(-level1_shape[0] // TILE)
    return {(0, 0), (cols - 1, rows - 1)}


def reference_levels() -> tuple[list[np.ndarray], float]:
    """The (H, W, 3) uint8 pixels of the fixture's 3 levels before encoding (absent tiles white),
    and the level-0 µm/px."""
    sys.path.insert(0, str(ROOT))
    from data_tools.slide_files.open import open_slide

    with open_slide(SOURCE) as reader:
        x0, y0, x1, y1 = CROP
        crop = reader.read_region(0, x0, y0, x1 - x0, y1 - y0)
        mpp = reader.mpp * DOWNSAMPLE
    levels = []
    for k in range(3):
        size = ((x1 - x0) // (DOWNSAMPLE * 2**k), (y1 - y0) // (DOWNSAMPLE * 2**k))
        levels.append(np.array(Image.fromarray(crop).resize(size, Image.Resampling.BOX)))
    for tx, ty in _absent(levels[1].shape):
        levels[1][ty * TILE : (ty + 1) * TILE, tx * TILE : (tx + 1) * TILE] = 255
    return levels, mpp


def main() -> int:
    levels, mpp = reference_levels()
    OUT.mkdir(exist_ok=True)
    # level 0: every tile, stored column by column
    cols, rows = -(-levels[0].shape[1] // TILE), -(-levels[0].shape[0] // TILE)
    _write(0, levels[0], mpp, JPEGBaseline8Bit, [(tx, ty) for tx in range(cols) for ty in range(rows)])
    # level 1: sparse, the first and last tiles absent (painted white in the reference)
    cols, rows = -(-levels[1].shape[1] // TILE), -(-levels[1].shape[0] // TILE)
    absent = _absent(levels[1].shape)
    present = [(tx, ty) for ty in range(rows) for tx in range(cols) if (tx, ty) not in absent]
    _write(1, levels[1], mpp, JPEG2000, present)  # the absent tiles are white already: not stored
    # level 2: TILED_FULL
    _write(2, levels[2], mpp, JPEGBaseline8Bit, None)
    total = sum(f.stat().st_size for f in OUT.iterdir())
    print(f"wrote {OUT}: {', '.join(f'{lv.shape[1]}×{lv.shape[0]}' for lv in levels)} px, {total / 1024:.0f} KiB")
    return 0


if __name__ == "__main__":
    sys.exit(main())
