"""Read DICOM whole-slide images (VL Whole Slide Microscopy) as 8-bit RGB, through wsidicom.

This module's one job: give a DICOM WSI the interface of :class:`data_tools.slide_files.base.SlideReader`
(``levels``, ``mpp``, ``read_level``, ``read_region``), so that ``data_tools info`` / ``build``
(dense and tiled) read it like a TIFF. wsidicom (Apache-2.0, the optional extra ``dicom``:
``pip install 'histojax[dicom]'``) parses the instances and decodes the frames (JPEG, JPEG 2000,
JPEG-LS, uncompressed ...), honouring ``TILED_SPARSE`` frame positions whatever their order; tiles
a sparse instance leaves out come back as white background.

A slide is either a folder holding the instances of one slide (one file per pyramid level, as
archives such as IDC / TCIA ship them; other files are ignored) or one ``.dcm`` file of it, in which
case every DICOM file of the same series in that folder is opened with it (as OpenSlide does).

When wsidicom cannot open the files (no ``ImageType``, UIDs over 64 characters: files OpenSlide refuses
too), each instance is read with pydicom instead, as pathml does: its frames placed at their Per-frame
Functional Groups' plane positions (row-major for ``TILED_FULL``), decoded with imagecodecs, with one
warning saying why; an instance missing an attribute needed to place its frames is refused naming it.

Units as in :mod:`data_tools.slide_files.tiff`: pixels of the level read, ``downsample`` in level-0 px per
level px, ``mpp`` in µm per level-0 px. Every problem with the files raises
:class:`data_tools.errors.SlideError` naming the path, in one line.
"""

from __future__ import annotations

import os
import warnings

import numpy as np

from data_tools.errors import SlideError
from data_tools.slide_files.base import LevelInfo, SlideReader, check_levels
from data_tools.slide_files.limits import MAX_TILES, check_size

__all__ = ["DicomSlideReader", "is_dicom", "INSTALL_HINT"]

INSTALL_HINT = "reading DICOM WSI needs the optional extra: pip install 'histojax[dicom]' (wsidicom)"
_WSI_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.77.1.6"
_MAX_FILES = 10_000  # files looked at in a folder
# transfer syntax UID -> compression name in the spelling LevelInfo uses for TIFF
_COMPRESSIONS = {
    "1.2.840.10008.1.2.1": "NONE",
    "1.2.840.10008.1.2": "NONE",
    "1.2.840.10008.1.2.4.50": "JPEG",
    "1.2.840.10008.1.2.4.51": "JPEG",
    "1.2.840.10008.1.2.4.57": "JPEG",
    "1.2.840.10008.1.2.4.70": "JPEG",
    "1.2.840.10008.1.2.4.80": "JPEGLS",
    "1.2.840.10008.1.2.4.81": "JPEGLS",
    "1.2.840.10008.1.2.4.90": "JPEG2000",
    "1.2.840.10008.1.2.4.91": "JPEG2000",
    "1.2.840.10008.1.2.4.201": "HTJ2K",
    "1.2.840.10008.1.2.4.202": "HTJ2K",
    "1.2.840.10008.1.2.4.203": "HTJ2K",
    "1.2.840.10008.1.2.5": "RLE",
    "1.2.840.10008.1.2.4.110": "JPEGXL",
    "1.2.840.10008.1.2.4.112": "JPEGXL",
}


def _has_dicom_magic(path: str) -> bool:
    """True when the file starts with the DICOM preamble + ``DICM`` (bytes 128..131)."""
    try:
        with open(path, "rb") as f:
            return f.read(132)[128:132] == b"DICM"
    except OSError:
        return False


def _dicom_files(folder: str) -> list[str]:
    """The DICOM files directly in ``folder``, sorted by name."""
    try:
        names = sorted(os.listdir(folder))[:_MAX_FILES]
    except OSError as exc:
        raise SlideError(folder, f"cannot list the folder: {exc}") from exc
    paths = (os.path.join(folder, n) for n in names)
    return [p for p in paths if os.path.isfile(p) and _has_dicom_magic(p)]


def is_dicom(path: str | os.PathLike) -> bool:
    """True when ``path`` is a DICOM file, or a folder holding DICOM files (and no bundle)."""
    path = os.fspath(path)
    if os.path.isdir(path):
        return not os.path.isfile(os.path.join(path, "metadata.json")) and bool(_dicom_files(path))
    return _has_dicom_magic(path)


def _series_files(path: str) -> list[str]:
    """For one DICOM file: it and the DICOM files beside it of the same series (refusing non-WSI)."""
    import pydicom

    try:
        head = pydicom.dcmread(path, stop_before_pixels=True, specific_tags=["SOPClassUID", "SeriesInstanceUID"])
        sop_class, series = str(head.get("SOPClassUID", "")), str(head.get("SeriesInstanceUID", ""))
    except Exception as exc:  # pydicom errors: corrupt header
        raise SlideError(path, f"DICOM header unreadable ({type(exc).__name__}: {exc})") from exc
    if sop_class != _WSI_SOP_CLASS:
        raise SlideError(
            path,
            f"a DICOM file but not a whole-slide image (SOP class {sop_class or 'missing'}, "
            "need VL Whole Slide Microscopy Image Storage)",
        )
    files = [path]
    for other in _dicom_files(os.path.dirname(os.path.abspath(path))):
        if os.path.samefile(other, path):
            continue
        try:
            other_head = pydicom.dcmread(other, stop_before_pixels=True, specific_tags=["SeriesInstanceUID"])
        except Exception:  # an unreadable neighbour is not part of this slide
            continue
        if str(other_head.get("SeriesInstanceUID", "")) == series:
            files.append(other)
    return files


class DicomSlideReader(SlideReader):
    """An open DICOM WSI (a folder of instances, or one instance file and its series).

    Attributes as :class:`data_tools.slide_files.base.SlideReader`; ``format`` is ``"dicom-wsi"``; ``levels``
    are the levels of the first pyramid, finest first, ``tile_size`` their frame size and
    ``compression`` named from the transfer syntax (``"JPEG"``, ``"JPEG2000"``, ``"NONE"`` ...).
    """

    def __init__(self, path: str | os.PathLike):  # noqa: D107 (opens the file)
        self.path = os.fspath(path)
        self._handle = None  # the open wsidicom.WsiDicom (SlideReader's name for the open handle)
        self.format = "dicom-wsi"
        try:
            from wsidicom import WsiDicom
        except ImportError as exc:
            raise SlideError(self.path, f"is DICOM; {INSTALL_HINT}") from exc
        if not os.path.exists(self.path):
            raise SlideError(self.path, "file not found")
        with warnings.catch_warnings():  # pydicom warns for each UID over 64 characters; one warning says so
            warnings.filterwarnings(
                "ignore",
                message=r"The value length \(\d+\) exceeds the maximum length of 64 "
                "allowed for VR UI",
                category=UserWarning,
            )
            self._open(WsiDicom)

    def _open(self, WsiDicom) -> None:  # noqa: N803 (the class)
        files = _dicom_files(self.path) if os.path.isdir(self.path) else _series_files(self.path)
        if not files:
            raise SlideError(self.path, "no DICOM file in the folder")
        try:
            self._handle = WsiDicom.open(files)
            self._levels = sorted(self._handle.levels, key=lambda lv: lv.size.width, reverse=True)
            self.levels = _level_infos(self._levels)
            check_levels(self.path, self.levels)
            self.mpp = _mpp(self._handle)
            for k, lv in enumerate(self.levels):  # the last frame of a TILED_FULL instance: catches truncation
                self._decode_window(k, lv.width - 1, lv.height - 1, lv.width, lv.height)
        except SlideError:
            self.close()
            raise
        except Exception as exc:  # wsidicom / pydicom / OS errors: never escape raw
            self.close()
            problem = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            self._open_frames(files, problem, exc)  # e.g. no ImageType: frames placed by their positions

    def _open_frames(self, files: list[str], problem: str, exc: Exception) -> None:
        """Read the instances with pydicom, each frame where its plane position says (see
        :class:`_FrameLevel`), after wsidicom found no level in them (``problem``); a warning says why."""
        levels = []
        for f in files:
            try:
                level = _FrameLevel.open(f)
            except SlideError as e:
                raise SlideError(
                    self.path,
                    f"no readable VL Whole Slide Microscopy image (wsidicom: {problem}); "
                    f"{e.problem if os.path.samefile(e.path, self.path) else e}",
                ) from exc
            if level is not None:
                levels.append(level)
        levels.sort(key=lambda lv: (-lv.width, -lv.height))
        levels = [lv for i, lv in enumerate(levels) if i == 0 or lv.width != levels[i - 1].width]  # focal planes
        if not levels:
            raise SlideError(
                self.path,
                f"no readable VL Whole Slide Microscopy image (wsidicom: {problem}); "
                "no pyramid level in it (only label / overview / thumbnail or non-WSI "
                "instances)",
            ) from exc
        why = sorted({w for lv in levels for w in lv.why})
        self._handle = _FrameLevels(levels)  # the open handle, as SlideReader expects one
        w0, h0 = levels[0].width, levels[0].height
        self.levels = [
            LevelInfo(
                width=lv.width,
                height=lv.height,
                downsample=1.0 if k == 0 else (w0 / lv.width + h0 / lv.height) / 2.0,
                tile_size=lv.tile,
                compression=lv.compression,
            )
            for k, lv in enumerate(levels)
        ]
        check_levels(self.path, self.levels)
        self.mpp = levels[0].mpp
        warnings.warn(
            f"{self.path}: wsidicom cannot open it ({'; '.join(why) or problem}); read with pydicom, "
            "each frame where its plane position says",
            stacklevel=5,
        )
        for k, lv in enumerate(self.levels):  # decode the last frame: catches truncation at open
            self._decode_window(k, lv.width - 1, lv.height - 1, lv.width, lv.height)

    def __repr__(self) -> str:
        return f"DicomSlideReader({self.path!r}, levels={len(self.levels)})"

    def _decode_window(self, level: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """RGB pixels of the in-bounds window [y0:y1, x0:x1] of ``level``: (y1-y0, x1-x0, 3) uint8."""
        if isinstance(self._handle, _FrameLevels):
            return self._handle.levels[level].window(x0, y0, x1, y1)
        lv = self._levels[level]
        try:
            pixels = self._handle.read_region((x0, y0), lv.level, (x1 - x0, y1 - y0), as_array=True)
        except Exception as exc:  # wsidicom / codec / OS errors (e.g. a truncated file)
            raise SlideError(
                self.path,
                f"cannot decode level {level} frames ({self.levels[level].compression}): "
                f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}; "
                "file truncated or corrupt",
            ) from exc
        pixels = np.asarray(pixels)
        if pixels.ndim == 2:
            pixels = pixels[..., None]
        if pixels.shape[:2] != (y1 - y0, x1 - x0) or pixels.shape[2] not in (1, 3, 4) or pixels.dtype != np.uint8:
            raise SlideError(
                self.path,
                f"level {level} decoded to {pixels.shape} {pixels.dtype}, not 8-bit "
                f"grey / RGB of {x1 - x0}×{y1 - y0} px",
            )
        if pixels.shape[2] == 1:
            pixels = np.repeat(pixels, 3, axis=2)
        return np.ascontiguousarray(pixels[..., :3])


def _mpp(wsi) -> float | None:
    """µm per level-0 px from the pixel spacing, or None when the file gives none usable."""
    try:
        mpp = float(wsi.mpp.width)
    except Exception:  # wsidicom raises when no level states a pixel spacing
        return None
    return mpp if np.isfinite(mpp) and mpp > 0 else None


def _level_infos(levels) -> list[LevelInfo]:
    """LevelInfo of each wsidicom Level (finest first)."""
    w0, h0 = levels[0].size.width, levels[0].size.height
    infos = []
    for lv in levels:
        w, h = int(lv.size.width), int(lv.size.height)
        syntax = str(lv.default_instance.image_data.transfer_syntax)
        infos.append(
            LevelInfo(
                width=w,
                height=h,
                downsample=1.0 if (w, h) == (w0, h0) else (w0 / w + h0 / h) / 2.0,
                tile_size=(int(lv.tile_size.width), int(lv.tile_size.height)),
                compression=_COMPRESSIONS.get(syntax, syntax),
            )
        )
    return infos


# (keyword, tag) of the attributes without which the frames of an instance cannot be placed
_ESSENTIAL = (
    ("Rows", "(0028,0010)"),
    ("Columns", "(0028,0011)"),
    ("SamplesPerPixel", "(0028,0002)"),
    ("BitsAllocated", "(0028,0100)"),
    ("TotalPixelMatrixColumns", "(0048,0006)"),
    ("TotalPixelMatrixRows", "(0048,0007)"),
)
_NOT_PYRAMID = {"LABEL", "OVERVIEW", "THUMBNAIL"}  # ImageType value 3 of images that are no pyramid level


class _FrameLevel:
    """One VL Whole Slide Microscopy instance read with pydicom, as pathml does when OpenSlide and
    wsidicom cannot: its ``TotalPixelMatrixColumns`` × ``TotalPixelMatrixRows`` px (``width``,
    ``height``) tiled by ``Columns`` × ``Rows`` px frames (``tile``), each placed at the position of its
    Per-frame Functional Groups' ``PlanePositionSlideSequence`` (1-based level px), or row-major for
    ``TILED_FULL``; absent frames are white. Frames are decoded with imagecodecs (JPEG, JPEG 2000,
    JPEG-LS, ...) or read as 8-bit native pixels; the compressed frames of the instance are held in
    memory once the first is decoded. ``why`` lists what kept wsidicom from it (no ``ImageType``, UIDs
    over 64 characters)."""

    def __init__(self, path: str, ds, positions: np.ndarray, why: list[str]):
        self.path, self._ds, self.positions, self.why = path, ds, positions, why
        self.width, self.height = int(ds.TotalPixelMatrixColumns), int(ds.TotalPixelMatrixRows)
        self.tile = (int(ds.Columns), int(ds.Rows))
        self.syntax = str(ds.file_meta.get("TransferSyntaxUID", "1.2.840.10008.1.2.1"))
        self.compression = _COMPRESSIONS.get(self.syntax, self.syntax)
        self.mpp = _spacing_um(ds)
        self._frames: list[bytes] | None = None

    @classmethod
    def open(cls, path: str) -> "_FrameLevel | None":
        """The level of the instance at ``path``, None for a label / overview / thumbnail image;
        SlideError naming the first missing essential attribute."""
        import pydicom

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # pydicom: "value length (65) exceeds the maximum ... for VR UI"
                ds = pydicom.dcmread(path, defer_size="64 KB")
                image_type = [str(v).upper() for v in (ds.get("ImageType") or [])]
                sop_class = str(ds.get("SOPClassUID", ""))
                missing = [f"{k} {tag}" for k, tag in _ESSENTIAL if ds.get(k) in (None, "")]
                has_pixels = "PixelData" in ds
        except Exception as exc:  # pydicom errors: a corrupt or truncated header
            raise SlideError(path, f"DICOM header unreadable ({type(exc).__name__}: {exc})") from exc
        if sop_class != _WSI_SOP_CLASS or (len(image_type) > 2 and image_type[2] in _NOT_PYRAMID):
            return None  # another kind of DICOM in the folder (annotations, segmentations), or no pyramid level
        if missing:
            raise SlideError(
                path,
                f"missing the attribute {missing[0]}: cannot place the frames"
                + (f" (also missing: {', '.join(missing[1:])})" if missing[1:] else ""),
            )
        if not has_pixels:
            raise SlideError(path, "missing the attribute PixelData (7FE0,0010): no frames")
        if int(ds.BitsAllocated) != 8 or int(ds.SamplesPerPixel) not in (1, 3):
            raise SlideError(
                path, f"{ds.BitsAllocated}-bit pixels of {ds.SamplesPerPixel} samples; 8-bit grey or RGB needed"
            )
        try:  # the shared limits, before any array of the declared sizes is made
            check_size(path, int(ds.TotalPixelMatrixColumns), int(ds.TotalPixelMatrixRows), "the image")
            check_size(path, int(ds.Columns), int(ds.Rows), "a frame")
            frames = int(ds.get("NumberOfFrames") or 1)
        except (TypeError, ValueError) as exc:
            raise SlideError(path, f"a size attribute is not a number ({exc})") from exc
        if not 0 < frames <= MAX_TILES:
            raise SlideError(path, f"declares {frames:,} frames, outside the limit of 1..{MAX_TILES:,}")
        why = [] if image_type else ["no ImageType (0008,0008)"]
        long_uids = [
            k
            for k in ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID", "FrameOfReferenceUID")
            if len(str(ds.get(k) or "")) > 64
        ]
        why += [f"UIDs over 64 characters ({', '.join(long_uids)})"] if long_uids else []
        return cls(path, ds, _frame_positions(path, ds), why)

    def _frame(self, i: int) -> np.ndarray:
        """Frame ``i`` decoded: (Rows, Columns, 3) uint8."""
        import imagecodecs
        from pydicom.encaps import generate_frames

        ds, (tw, th) = self._ds, self.tile
        try:
            if self._frames is None:
                n = int(ds.get("NumberOfFrames") or 1)
                if ds.file_meta.TransferSyntaxUID.is_encapsulated:
                    self._frames = list(generate_frames(ds.PixelData, number_of_frames=n))
                else:
                    data, size = ds.PixelData, tw * th * int(ds.SamplesPerPixel)
                    self._frames = [data[k * size : (k + 1) * size] for k in range(n)]
            data = self._frames[i]
            if ds.file_meta.TransferSyntaxUID.is_encapsulated:
                tile = np.asarray(imagecodecs.imread(data))
            else:
                tile = np.frombuffer(data, np.uint8).reshape(th, tw, int(ds.SamplesPerPixel))
        except Exception as exc:  # pydicom / codec errors: a truncated or corrupt frame
            raise SlideError(
                self.path,
                f"cannot decode frame {i} ({self.compression}): {type(exc).__name__}: "
                f"{str(exc).splitlines()[0] if str(exc) else ''}; file truncated or corrupt",
            ) from exc
        if tile.ndim == 2:
            tile = tile[..., None]
        if tile.shape[:2] != (th, tw) or tile.dtype != np.uint8:
            raise SlideError(self.path, f"frame {i} decoded to {tile.shape} {tile.dtype}, not {tw}×{th} 8-bit")
        return np.repeat(tile, 3, axis=2) if tile.shape[2] == 1 else tile[..., :3]

    def window(self, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """RGB pixels of [y0:y1, x0:x1] (level px): (y1-y0, x1-x0, 3) uint8, white where no frame is."""
        out = np.full((y1 - y0, x1 - x0, 3), 255, np.uint8)
        tw, th = self.tile
        p = self.positions
        hit = np.nonzero((p[:, 0] < x1) & (p[:, 0] + tw > x0) & (p[:, 1] < y1) & (p[:, 1] + th > y0))[0]
        for i in hit:
            fx, fy, frame = (int(v) for v in p[i])
            tile = self._frame(frame)
            ax0, ay0, ax1, ay1 = max(fx, x0), max(fy, y0), min(fx + tw, x1), min(fy + th, y1)
            out[ay0 - y0 : ay1 - y0, ax0 - x0 : ax1 - x0] = tile[ay0 - fy : ay1 - fy, ax0 - fx : ax1 - fx]
        return out


class _FrameLevels:
    """The open handle of a slide read with pydicom: its :class:`_FrameLevel` list, finest first."""

    def __init__(self, levels: list[_FrameLevel]):
        self.levels = levels

    def close(self) -> None:
        self.levels = []


def _frame_positions(path: str, ds) -> np.ndarray:
    """(x, y, frame index) of every frame of the first focal plane, level px (0-based): from the
    Per-frame Functional Groups' plane positions, or row-major for ``TILED_FULL``."""
    tw, th = int(ds.Columns), int(ds.Rows)
    n = int(ds.get("NumberOfFrames") or 1)
    per_frame = ds.get("PerFrameFunctionalGroupsSequence")
    organisation = str(ds.get("DimensionOrganizationType") or "")
    if organisation == "TILED_FULL" or (not per_frame and not organisation):
        cols, rows = -(-int(ds.TotalPixelMatrixColumns) // tw), -(-int(ds.TotalPixelMatrixRows) // th)
        k = np.arange(min(n, cols * rows))
        return np.stack([k % cols * tw, k // cols * th, k], axis=1)
    if not per_frame:
        raise SlideError(
            path,
            f"missing the attribute PerFrameFunctionalGroupsSequence (5200,9230): {organisation} "
            "frames without positions",
        )
    if len(per_frame) != n:
        raise SlideError(path, f"PerFrameFunctionalGroupsSequence has {len(per_frame)} items for {n} frames")
    out, seen = [], set()
    for i, item in enumerate(per_frame):
        try:
            pos = item.PlanePositionSlideSequence[0]
            x, y = int(pos.ColumnPositionInTotalImagePixelMatrix) - 1, int(pos.RowPositionInTotalImagePixelMatrix) - 1
        except (AttributeError, IndexError, TypeError, ValueError) as exc:
            raise SlideError(
                path,
                f"frame {i}: missing the attribute PlanePositionSlideSequence (0048,021A) with "
                "Column / RowPositionInTotalImagePixelMatrix (0048,021E) / (0048,021F)",
            ) from exc
        if (x, y) not in seen:  # later focal planes / optical paths at the same position: the first kept
            seen.add((x, y))
            out.append((x, y, i))
    return np.asarray(out, dtype=np.int64).reshape(-1, 3)


def _spacing_um(ds) -> float | None:
    """µm per px of an instance from its shared Pixel Measures (or its imaged volume), None if absent."""
    try:
        spacing = float(ds.SharedFunctionalGroupsSequence[0].PixelMeasuresSequence[0].PixelSpacing[1]) * 1000.0
    except Exception:  # absent or malformed: try the imaged volume
        try:
            spacing = float(ds.ImagedVolumeWidth) * 1000.0 / int(ds.TotalPixelMatrixColumns)
        except Exception:
            return None
    return spacing if np.isfinite(spacing) and spacing > 0 else None
