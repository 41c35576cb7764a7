"""Read whole-slide image files (Aperio SVS, pyramidal TIFF, OME-TIFF) as 8-bit RGB; DICOM WSI in
:mod:`data_tools.slide_files.dicom`, behind the same interface (:func:`data_tools.slide_files.open.open_slide` picks).

This module's one job: open a slide file with tifffile, list its pyramid levels,
and decode whole levels or rectangular regions of a level into ``(H, W, 3)``
``uint8`` RGB arrays. Tile decoding is done by tifffile + imagecodecs (JPEG,
JPEG 2000 incl. Aperio's 33003/33005 variants, LZW, Deflate, ...).

Units used throughout:
  * sizes and coordinates are in pixels; ``x``/``y``/``width``/``height`` given to
    :meth:`~data_tools.slide_files.base.SlideReader.read_region` are pixels *of the level read*;
  * ``downsample`` is level-0 pixels per pixel of the level (level 0 = 1.0);
  * ``mpp`` is micrometres per level-0 pixel;
  * byte budgets (``max_bytes``) are bytes of decoded RGB output (H * W * 3).

Every problem with the file (not a TIFF, corrupt, truncated, unsupported pixel
format, over the decode budget) raises :class:`data_tools.errors.SlideError`
naming the file; mistakes in the arguments (level index out of range, negative
region size) raise ``ValueError``.
"""

from __future__ import annotations

import math
import os
import re
import stat
import warnings

import numpy as np
import tifffile

from data_tools.errors import SlideError
from data_tools.slide_files.base import MAX_DECODE_BYTES, LevelInfo, SlideReader, check_levels
from data_tools.slide_files.limits import MAX_SIDE, check_size

__all__ = ["TiffSlideReader"]

_SUPPORTED = (
    "histojax reads Aperio SVS, pyramidal TIFF and BigTIFF, OME-TIFF, Akoya QPTIFF, Hamamatsu NDPI and DICOM WSI"
)
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
_JPEG_COMPRESSIONS = {6, 7, 34892, 33007}  # need JPEGTables / header when decoding

# TIFF Photometric values
_MINISWHITE, _MINISBLACK, _RGB, _PALETTE, _YCBCR = 0, 1, 2, 3, 6
# ExtraSamples values
_ASSOC_ALPHA, _UNASSOC_ALPHA = 1, 2
_RESUNIT_CENTIMETER = 3

# micrometres per unit, for OME PhysicalSizeXUnit
_OME_UNIT_UM = {
    "µm": 1.0,
    "μm": 1.0,
    "um": 1.0,
    "micron": 1.0,
    "nm": 1e-3,
    "pm": 1e-6,
    "Å": 1e-4,
    "mm": 1e3,
    "cm": 1e4,
    "m": 1e6,
}


class TiffSlideReader(SlideReader):
    """An open SVS, pyramidal TIFF or OME-TIFF file; a :class:`~data_tools.slide_files.base.SlideReader` wrapping
    ``tifffile.TiffFile``.

    Attributes as :class:`~data_tools.slide_files.base.SlideReader`; ``format`` is ``"aperio-svs"``,
    ``"ome-tiff"``, ``"philips-tiff"`` or ``"tiff"``; ``levels`` are pyramid levels only (SVS thumbnail, label
    and macro images are not levels).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = os.fspath(path)
        self._handle: tifffile.TiffFile | None = None
        self._warned_missing: set[int] = set()
        _check_signature(self.path)
        try:
            self._handle = tifffile.TiffFile(self.path)
            self.format = _detect_format(self._handle)
            self._pages = _pyramid_pages(self.path, self._handle)
            self.levels = _level_infos(self._pages)
            check_levels(self.path, self.levels)
            self.mpp = _find_mpp(self._handle, self.format, self._pages[0])
        except SlideError:
            self.close()
            raise
        except Exception as exc:  # tifffile/imagecodecs/OS errors: never escape raw
            self.close()
            raise SlideError(
                self.path,
                f"format not recognised or file corrupt ({type(exc).__name__}: {exc}); {_SUPPORTED}",
            ) from exc

    def _decode_window(self, level: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """RGB pixels of the in-bounds window [y0:y1, x0:x1] of ``level``."""
        page = self._pages[level]
        info = self.levels[level]
        nsep, _, _, _, ncontig = page.shaped
        if page.is_tiled:
            seg_w, seg_h = page.tilewidth, page.tilelength
        else:
            seg_w, seg_h = info.width, min(page.rowsperstrip, info.height)
        across = math.ceil(info.width / seg_w)
        down = math.ceil(info.height / seg_h)
        offsets, bytecounts = page.dataoffsets, page.databytecounts
        if len(offsets) != nsep * across * down or len(bytecounts) != len(offsets):
            raise SlideError(
                self.path,
                f"level {level}: {len(offsets)} tile/strip offsets, expected {nsep * across * down}; file is corrupt",
            )
        raw = np.zeros((nsep, y1 - y0, x1 - x0, ncontig), dtype=page.dtype)
        missing = np.zeros((y1 - y0, x1 - x0), dtype=bool)  # tiles absent from the file
        decode = page.decode
        kwargs = {}
        if page.compression in _JPEG_COMPRESSIONS:
            kwargs = {"jpegtables": page.jpegtables, "jpegheader": page.jpegheader}
        fh = self._handle.filehandle
        filesize = fh.size
        for s in range(nsep):
            for ty in range(y0 // seg_h, (y1 - 1) // seg_h + 1):
                for tx in range(x0 // seg_w, (x1 - 1) // seg_w + 1):
                    index = (s * down + ty) * across + tx
                    offset, count = int(offsets[index]), int(bytecounts[index])
                    # destination window of this segment, clipped to the request
                    sy0, sx0 = ty * seg_h, tx * seg_w
                    cy0, cy1 = max(sy0, y0), min(sy0 + seg_h, y1)
                    cx0, cx1 = max(sx0, x0), min(sx0 + seg_w, x1)
                    if offset == 0 or count == 0:
                        missing[cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0] = True
                        continue
                    if offset + count > filesize:
                        raise SlideError(
                            self.path,
                            f"level {level} tile/strip {index} ends at byte {offset + count} "
                            f"but the file has {filesize} bytes: file is truncated",
                        )
                    try:
                        with fh.lock:
                            fh.seek(offset)
                            data = fh.read(count)
                        seg, _, _ = decode(data, index, **kwargs)
                    except Exception as exc:  # tifffile / imagecodecs errors
                        raise SlideError(
                            self.path,
                            f"cannot decode level {level} tile/strip {index} "
                            f"({info.compression}): {type(exc).__name__}: {exc}",
                        ) from exc
                    seg = np.asarray(seg)  # (depth=1, rows, cols, ncontig)
                    if seg.ndim != 4 or seg.shape[1] < cy1 - sy0 or seg.shape[2] < cx1 - sx0:
                        raise SlideError(
                            self.path,
                            f"level {level} tile/strip {index} decoded to shape {seg.shape}, "
                            f"too small for its place in the image: file is corrupt",
                        )
                    raw[s, cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0, :] = seg[
                        0, cy0 - sy0 : cy1 - sy0, cx0 - sx0 : cx1 - sx0, :
                    ]
        pixels = raw[0] if nsep == 1 else np.moveaxis(raw[..., 0], 0, -1)
        rgb = _to_rgb(pixels, page)
        if missing.any():
            rgb[missing] = 255
            if level not in self._warned_missing:
                self._warned_missing.add(level)
                warnings.warn(
                    f"{self.path}: level {level} has tiles/strips absent from the file (offset or byte "
                    "count 0); they are read as white",
                    stacklevel=3,
                )
        return rgb


# ---------------------------------------------------------------------------
# opening


def _check_signature(path: str) -> None:
    """Reject missing files, directories and non-TIFF files with a helpful SlideError."""
    if os.path.isdir(path):
        raise SlideError(path, f"is a folder with no DICOM file in it, not a slide; {_SUPPORTED}")
    try:
        if not stat.S_ISREG(os.stat(path).st_mode):  # a FIFO would block open() forever
            raise SlideError(path, "not a regular file (a FIFO, socket or device): not a slide")
        with open(path, "rb") as f:
            head = f.read(132)
    except FileNotFoundError as exc:
        raise SlideError(path, "file not found") from exc
    except OSError as exc:
        raise SlideError(path, f"cannot read file: {exc}") from exc
    if head[128:132] == b"DICM":
        raise SlideError(path, "is DICOM: open it with data_tools.slide_files.open.open_slide, not TiffSlideReader")
    if head[:4] not in _TIFF_MAGICS:
        raise SlideError(path, f"format not recognised (not a TIFF file); {_SUPPORTED}")


def _detect_format(tif: tifffile.TiffFile) -> str:
    if tif.is_svs:
        return "aperio-svs"
    if tif.is_ome:
        return "ome-tiff"
    if tif.is_philips:
        return "philips-tiff"
    return "tiff"


def _pyramid_pages(path: str, tif: tifffile.TiffFile) -> list[tifffile.TiffPage]:
    """First page of each level of the main series, validated, finest first."""
    series = tif.series
    if not series:
        raise SlideError(path, f"no image found in the TIFF (file truncated or corrupt); {_SUPPORTED}")
    pages = []
    for i, level in enumerate(series[0].levels):
        if len(level.pages) != 1:
            raise SlideError(
                path,
                f"unsupported: level {i} has {len(level.pages)} image planes (channels / z / time "
                "stored as separate pages); convert to 8-bit RGB first",
            )
        page = level.pages[0]
        if page is None:
            raise SlideError(path, f"level {i} has no image data: file is corrupt")
        if not isinstance(page, tifffile.TiffPage):
            page = page.aspage()
        _validate_page(path, i, page)
        pages.append(page)
    if not pages:
        raise SlideError(path, f"no image found in the TIFF (file truncated or corrupt); {_SUPPORTED}")
    # finest first (tifffile already orders them so; make it a guarantee)
    pages.sort(key=lambda p: p.imagewidth * p.imagelength, reverse=True)
    return pages


def _validate_page(path: str, level: int, page: tifffile.TiffPage) -> None:
    """Refuse absurd sizes and pixel formats that do not map cleanly to 8-bit RGB."""
    w, h = page.imagewidth, page.imagelength
    check_size(path, w, h, f"level {level}")  # the limits every reader shares (level 0: its area too)
    if page.imagedepth != 1:
        raise SlideError(path, f"unsupported: level {level} is a volume (depth {page.imagedepth})")
    if page.is_tiled:
        tw, th = page.tilewidth, page.tilelength
        if not (0 < tw <= MAX_SIDE and 0 < th <= MAX_SIDE) or page.tiledepth != 1:
            raise SlideError(path, f"level {level} has absurd tile size {tw}×{th}")
        seg_px = tw * th
    else:
        seg_px = w * min(page.rowsperstrip or h, h)
    expected = _segment_count(page)
    if len(page.dataoffsets) != expected or len(page.databytecounts) != len(page.dataoffsets):
        raise SlideError(
            path,
            f"level {level}: {len(page.dataoffsets)} tile/strip offsets and "
            f"{len(page.databytecounts)} byte counts, expected {expected} (offsets tag missing or short): "
            "file is corrupt",
        )
    samples = page.samplesperpixel
    dtype = page.dtype
    what = f"level {level}: {samples} samples / dtype {dtype} / photometric {page.photometric.name}"
    unsupported = f"unsupported: {what}; convert to 8-bit RGB first"
    if dtype is None or samples > 4:
        raise SlideError(path, unsupported)
    photometric = int(page.photometric)
    if photometric == _PALETTE:
        ok = samples == 1 and dtype in (np.uint8, np.uint16) and page.colormap is not None
    elif photometric in (_MINISBLACK, _MINISWHITE):
        ok = samples in (1, 2) and dtype in (np.uint8, np.bool_)
    elif photometric == _RGB:
        ok = samples in (3, 4) and dtype == np.uint8
    elif photometric == _YCBCR:  # tifffile converts JPEG YCbCr to RGB while decoding
        ok = samples == 3 and dtype == np.uint8 and page.compression in _JPEG_COMPRESSIONS
    else:
        ok = False
    if not ok:
        raise SlideError(path, unsupported)
    if seg_px * samples * dtype.itemsize > MAX_DECODE_BYTES:
        raise SlideError(path, f"level {level}: one tile/strip would decode to more than {MAX_DECODE_BYTES} bytes")


def _segment_count(page: tifffile.TiffPage) -> int:
    """Number of tiles (or strips) of a page, all sample planes: what its offsets tag must list."""
    w, h = page.imagewidth, page.imagelength
    if page.is_tiled:
        seg_w, seg_h = page.tilewidth, page.tilelength
    else:
        seg_w, seg_h = w, min(page.rowsperstrip or h, h)
    return page.shaped[0] * math.ceil(w / seg_w) * math.ceil(h / seg_h)


def _level_infos(pages: list[tifffile.TiffPage]) -> list[LevelInfo]:
    w0, h0 = pages[0].imagewidth, pages[0].imagelength
    infos = []
    for page in pages:
        w, h = page.imagewidth, page.imagelength
        infos.append(
            LevelInfo(
                width=int(w),
                height=int(h),
                downsample=1.0 if (w, h) == (w0, h0) else (w0 / w + h0 / h) / 2.0,
                tile_size=(int(page.tilewidth), int(page.tilelength)) if page.is_tiled else None,
                compression=page.compression.name,
            )
        )
    return infos


# ---------------------------------------------------------------------------
# resolution


def _positive(value: float) -> float | None:
    return value if math.isfinite(value) and value > 0 else None


def _find_mpp(tif: tifffile.TiffFile, fmt: str, page0: tifffile.TiffPage) -> float | None:
    """µm per level-0 pixel from Aperio MPP, OME PhysicalSizeX, or XResolution in px/cm."""
    if fmt == "aperio-svs":
        m = re.search(r"\bMPP\s*=\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)", page0.description or "")
        if m and (mpp := _positive(float(m.group(1)))):
            return mpp
    if fmt == "ome-tiff":
        mpp = _ome_mpp(tif.ome_metadata or "")
        if mpp:
            return mpp
    xres = page0.tags.get("XResolution")
    unit = page0.tags.get("ResolutionUnit")
    if xres is not None and unit is not None and int(unit.value) == _RESUNIT_CENTIMETER:
        num, den = xres.value
        if num > 0 and den > 0:
            return _positive(1e4 * den / num)  # px/cm -> µm/px
    return None


def _ome_mpp(xml: str) -> float | None:
    """PhysicalSizeX of the first OME ``Pixels`` element, in µm (None if absent / unparseable)."""
    m = re.search(r"<(?:\w+:)?Pixels\b([^>]*)>", xml)
    if not m:
        return None
    attrs = dict(re.findall(r'(\w+)\s*=\s*"([^"]*)"', m.group(1)))
    try:
        size = float(attrs["PhysicalSizeX"])
    except (KeyError, ValueError):
        return None
    scale = _OME_UNIT_UM.get(attrs.get("PhysicalSizeXUnit", "µm"))
    return None if scale is None else _positive(size * scale)


# ---------------------------------------------------------------------------
# pixel conversion


def _composite_on_white(color: np.ndarray, alpha: np.ndarray, associated: bool) -> np.ndarray:
    """Blend ``color`` (H, W, C) over white using ``alpha`` (H, W); uint8 result."""
    c = color.astype(np.float32)
    a = alpha.astype(np.float32)[..., None] / 255.0
    out = c + 255.0 * (1.0 - a) if associated else c * a + 255.0 * (1.0 - a)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _to_rgb(pixels: np.ndarray, page: tifffile.TiffPage) -> np.ndarray:
    """Convert decoded samples (H, W, S) of a validated page to (H, W, 3) uint8 RGB."""
    photometric = int(page.photometric)
    extras = tuple(int(e) for e in (page.extrasamples or ()))
    alpha_kind = extras[0] if extras else 0
    if photometric == _PALETTE:
        cmap = np.asarray(page.colormap)  # (3, 2**bits) uint16
        if cmap.max() > 255:
            cmap = cmap / 257.0
        lut = np.clip(np.rint(cmap.T), 0, 255).astype(np.uint8)  # (N, 3)
        index = np.minimum(pixels[..., 0], len(lut) - 1)
        return lut[index]
    if photometric in (_MINISBLACK, _MINISWHITE):
        gray = pixels[..., 0]
        gray = gray.astype(np.uint8) * 255 if gray.dtype == np.bool_ else gray
        if photometric == _MINISWHITE:
            gray = 255 - gray
        rgb = np.repeat(gray[..., None], 3, axis=-1)
        if pixels.shape[-1] == 2 and alpha_kind in (_ASSOC_ALPHA, _UNASSOC_ALPHA):
            alpha = pixels[..., 1]
            alpha = alpha.astype(np.uint8) * 255 if alpha.dtype == np.bool_ else alpha
            rgb = _composite_on_white(rgb, alpha, alpha_kind == _ASSOC_ALPHA)
        return np.ascontiguousarray(rgb)
    # RGB (or JPEG YCbCr, which tifffile already returns as RGB)
    rgb = pixels[..., :3]
    if pixels.shape[-1] == 4 and alpha_kind in (_ASSOC_ALPHA, _UNASSOC_ALPHA):
        return _composite_on_white(rgb, pixels[..., 3], alpha_kind == _ASSOC_ALPHA)
    return np.ascontiguousarray(rgb)
