"""Read DICOM whole-slide images (VL Whole Slide Microscopy) as 8-bit RGB, through wsidicom.

This module's one job: give a DICOM WSI the interface of :class:`data_tools.slides.SlideReader`
(``levels``, ``mpp``, ``read_level``, ``read_region``), so that ``data_tools info`` / ``build``
(dense and tiled) read it like a TIFF. wsidicom (Apache-2.0, the optional extra ``dicom``:
``pip install 'histojax[dicom]'``) parses the instances and decodes the frames (JPEG, JPEG 2000,
JPEG-LS, uncompressed ...), honouring ``TILED_SPARSE`` frame positions whatever their order; tiles
a sparse instance leaves out come back as white background.

A slide is either a folder holding the instances of one slide (one file per pyramid level, as
archives such as IDC / TCIA ship them; other files are ignored) or one ``.dcm`` file of it, in which
case every DICOM file of the same series in that folder is opened with it (as OpenSlide does).

Units as in :mod:`data_tools.slides`: pixels of the level read, ``downsample`` in level-0 px per
level px, ``mpp`` in µm per level-0 px. Every problem with the files raises
:class:`data_tools.errors.SlideError` naming the path, in one line.
"""
from __future__ import annotations

import os

import numpy as np

from data_tools.errors import SlideError
from data_tools.slides import LevelInfo, SlideReader, _check_levels

__all__ = ["DicomSlideReader", "is_dicom", "INSTALL_HINT"]

INSTALL_HINT = "reading DICOM WSI needs the optional extra: pip install 'histojax[dicom]' (wsidicom)"
_WSI_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.77.1.6"
_MAX_FILES = 10_000  # files looked at in a folder
# transfer syntax UID -> compression name in the spelling LevelInfo uses for TIFF
_COMPRESSIONS = {
    "1.2.840.10008.1.2.1": "NONE", "1.2.840.10008.1.2": "NONE",
    "1.2.840.10008.1.2.4.50": "JPEG", "1.2.840.10008.1.2.4.51": "JPEG", "1.2.840.10008.1.2.4.57": "JPEG",
    "1.2.840.10008.1.2.4.70": "JPEG", "1.2.840.10008.1.2.4.80": "JPEGLS", "1.2.840.10008.1.2.4.81": "JPEGLS",
    "1.2.840.10008.1.2.4.90": "JPEG2000", "1.2.840.10008.1.2.4.91": "JPEG2000",
    "1.2.840.10008.1.2.4.201": "HTJ2K", "1.2.840.10008.1.2.4.202": "HTJ2K", "1.2.840.10008.1.2.4.203": "HTJ2K",
    "1.2.840.10008.1.2.5": "RLE", "1.2.840.10008.1.2.4.110": "JPEGXL", "1.2.840.10008.1.2.4.112": "JPEGXL",
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
        raise SlideError(path, f"a DICOM file but not a whole-slide image (SOP class {sop_class or 'missing'}, "
                               "need VL Whole Slide Microscopy Image Storage)")
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

    Attributes as :class:`data_tools.slides.SlideReader`; ``format`` is ``"dicom-wsi"``; ``levels``
    are the levels of the first pyramid, finest first, ``tile_size`` their frame size and
    ``compression`` named from the transfer syntax (``"JPEG"``, ``"JPEG2000"``, ``"NONE"`` ...).
    """

    def __init__(self, path: str | os.PathLike):  # noqa: D107 (replaces the TIFF opening)
        self.path = os.fspath(path)
        self._tif = None  # the open wsidicom.WsiDicom (SlideReader's name for the open handle)
        self.format = "dicom-wsi"
        try:
            from wsidicom import WsiDicom
        except ImportError as exc:
            raise SlideError(self.path, f"is DICOM; {INSTALL_HINT}") from exc
        if not os.path.exists(self.path):
            raise SlideError(self.path, "file not found")
        files = _dicom_files(self.path) if os.path.isdir(self.path) else _series_files(self.path)
        if not files:
            raise SlideError(self.path, "no DICOM file in the folder")
        try:
            self._tif = WsiDicom.open(files)
            self._levels = sorted(self._tif.levels, key=lambda lv: lv.size.width, reverse=True)
            self.levels = _level_infos(self._levels)
            _check_levels(self.path, self.levels)
            self.mpp = _mpp(self._tif)
            for k, lv in enumerate(self.levels):  # the last frame of a TILED_FULL instance: catches truncation
                self._decode_window(k, lv.width - 1, lv.height - 1, lv.width, lv.height)
        except SlideError:
            self.close()
            raise
        except Exception as exc:  # wsidicom / pydicom / OS errors: never escape raw
            self.close()
            problem = str(exc).splitlines()[0] if str(exc) else ""
            if "not found" in problem.lower() or isinstance(exc, (IndexError, KeyError)):
                problem = (f"no readable VL Whole Slide Microscopy image found ({type(exc).__name__}: {problem}); "
                           "truncated, not a slide, or a label / overview only")
            else:
                problem = f"DICOM WSI not readable ({type(exc).__name__}: {problem})"
            raise SlideError(self.path, problem) from exc

    def __repr__(self) -> str:
        return f"DicomSlideReader({self.path!r}, levels={len(self.levels)})"

    def _decode_window(self, level: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """RGB pixels of the in-bounds window [y0:y1, x0:x1] of ``level``: (y1-y0, x1-x0, 3) uint8."""
        lv = self._levels[level]
        try:
            pixels = self._tif.read_region((x0, y0), lv.level, (x1 - x0, y1 - y0), as_array=True)
        except Exception as exc:  # wsidicom / codec / OS errors (e.g. a truncated file)
            raise SlideError(self.path, f"cannot decode level {level} frames ({self.levels[level].compression}): "
                                        f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}; "
                                        "file truncated or corrupt") from exc
        pixels = np.asarray(pixels)
        if pixels.ndim == 2:
            pixels = pixels[..., None]
        if pixels.shape[:2] != (y1 - y0, x1 - x0) or pixels.shape[2] not in (1, 3, 4) or pixels.dtype != np.uint8:
            raise SlideError(self.path, f"level {level} decoded to {pixels.shape} {pixels.dtype}, not 8-bit "
                                        f"grey / RGB of {x1 - x0}×{y1 - y0} px")
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
        infos.append(LevelInfo(
            width=w, height=h, downsample=1.0 if (w, h) == (w0, h0) else (w0 / w + h0 / h) / 2.0,
            tile_size=(int(lv.tile_size.width), int(lv.tile_size.height)),
            compression=_COMPRESSIONS.get(syntax, syntax)))
    return infos
