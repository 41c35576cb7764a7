"""Which reader opens a slide: :func:`open_slide` picks the native TIFF reader (:mod:`data_tools.slide_files.tiff`), the DICOM
WSI reader (:mod:`data_tools.slide_files.dicom`) or OpenSlide (:mod:`data_tools.slide_files.openslide`), all behind
:class:`data_tools.slide_files.base.SlideReader`'s interface. Kept apart from the readers so that they import only their
base class (no import circle)."""

from __future__ import annotations

import os
import stat

from data_tools.errors import SlideError
from data_tools.slide_files.base import SlideReader
from data_tools.slide_files.dicom import DicomSlideReader, is_dicom
from data_tools.slide_files.openslide import (
    OPENSLIDE_EXTENSIONS,
    OpenSlideReader,
    openslide_available,
    openslide_module,
)
from data_tools.slide_files.tiff import TiffSlideReader

READERS = ("auto", "native", "openslide")
"""What :func:`open_slide` may read a slide with (``--reader``): ``auto`` (the native readers, OpenSlide for the
formats they do not read), ``native`` (tifffile / wsidicom only) or ``openslide`` (OpenSlide for any slide)."""


def open_slide(path: str | os.PathLike, reader: str | None = "auto") -> SlideReader:
    """Open a slide (SVS, pyramidal TIFF, OME-TIFF file; DICOM WSI file or folder, see
    :mod:`data_tools.slide_files.dicom`; MIRAX, SCN, BIF, VMS / VMU, SVSlide and Philips TIFF through OpenSlide, see
    :mod:`data_tools.slide_files.openslide`); raises SlideError if unreadable.

    ``reader``: ``"auto"`` (or None; the native readers, OpenSlide for the formats they do not read),
    ``"native"`` or ``"openslide"`` (any slide through OpenSlide: needs ``histojax[openslide]``)."""
    reader = reader or "auto"
    if reader not in READERS:
        raise ValueError(f"reader must be one of {READERS}, got {reader!r}")
    try:
        mode = os.stat(path).st_mode
    except OSError:
        mode = None  # missing or unreadable: the reader names the reason
    if mode is not None and not (stat.S_ISREG(mode) or stat.S_ISDIR(mode)):  # never open() a FIFO: it blocks
        raise SlideError(path, "not a regular file (a FIFO, socket or device): not a slide")
    if reader == "openslide":
        return OpenSlideReader(path)
    ext = os.path.splitext(os.fspath(path))[1].lower()
    if reader == "auto" and ext in OPENSLIDE_EXTENSIONS and mode is not None and stat.S_ISREG(mode):
        return OpenSlideReader(path)  # one line naming the extra when it is not installed
    if is_dicom(path):
        return DicomSlideReader(path)
    try:
        native = TiffSlideReader(path)
    except SlideError:
        if reader == "auto" and _openslide_vendor(path) not in (None, "generic-tiff"):
            try:  # a scanner's TIFF the native reader refuses (Philips, Leica, Ventana): OpenSlide's reading
                return OpenSlideReader(path)
            except SlideError:
                pass
        raise
    if reader == "auto" and native.format == "philips-tiff" and openslide_available():
        native.close()  # OpenSlide knows Philips TIFF's levels and the scanner's blank tiles
        return OpenSlideReader(path)
    return native


def _openslide_vendor(path) -> str | None:
    """OpenSlide's vendor name for ``path`` (``"philips"``, ``"leica"`` ...), or None (not installed, not
    recognised)."""
    openslide = openslide_module()
    if openslide is None:
        return None
    try:
        return openslide.OpenSlide.detect_format(os.fspath(path))
    except Exception:  # noqa: BLE001 - any trouble: not a slide OpenSlide reads
        return None
