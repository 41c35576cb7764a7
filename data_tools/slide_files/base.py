"""What every slide-file reader shares: the reader's interface and its format-independent reads
(:class:`SlideReader`: levels, regions, the decode limit :data:`MAX_DECODE_BYTES`), the description of a pyramid
level (:class:`LevelInfo`), the pyramid checks every reader applies to the levels a file declares
(:func:`check_levels`) and the human-readable summary ``data_tools info`` prints (:func:`describe`).

The readers themselves, one subclass each: :mod:`data_tools.slide_files.tiff` (SVS, pyramidal TIFF, OME-TIFF),
:mod:`data_tools.slide_files.dicom`
(DICOM WSI) and :mod:`data_tools.slide_files.openslide` (the formats OpenSlide reads); :func:`data_tools.slide_files.open.open_slide`
picks one. Units: pixels of the level concerned; ``downsample`` in level-0 px per level px.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data_tools.errors import SlideError
from data_tools.slide_files.limits import check_level_sizes

__all__ = ["MAX_DECODE_BYTES", "LevelInfo", "SlideReader", "check_levels", "describe"]

MAX_DECODE_BYTES = 4 * 1024**3
"""Default limit (bytes of decoded RGB, H * W * 3) for :meth:`SlideReader.read_level`."""


@dataclass(frozen=True)
class LevelInfo:
    """One pyramid level of a slide.

    Attributes:
        width: width of this level in pixels.
        height: height of this level in pixels.
        downsample: level-0 pixels per pixel of this level (1.0 for level 0),
            the mean of the width and height ratios (OpenSlide's convention).
        tile_size: ``(tile width, tile height)`` in pixels, or ``None`` when the
            level is stored in strips.
        compression: TIFF compression name as tifffile spells it, e.g. ``"JPEG"``,
            ``"JPEG2000"``, ``"APERIO_JPEG2000_RGB"``, ``"NONE"``, ``"LZW"``,
            ``"ADOBE_DEFLATE"``.
    """

    width: int
    height: int
    downsample: float
    tile_size: tuple[int, int] | None
    compression: str


class SlideReader:
    """An open slide file, whatever its format: the interface every reader keeps (a context manager).

    A subclass opens the file in its ``__init__`` (setting ``path``, ``format``, ``levels``, ``mpp`` and the open
    handle ``_handle``, which has a ``close()``) and decodes pixels in :meth:`_decode_window`; this class reads whole
    levels and regions (white outside the level, the decode limits) through it. The readers:
    :class:`~data_tools.slide_files.tiff.TiffSlideReader`, :class:`~data_tools.slide_files.dicom.DicomSlideReader`,
    :class:`~data_tools.slide_files.openslide.OpenSlideReader`.

    Attributes:
        path: the file path as given (``str``).
        format: the format's name (``"aperio-svs"``, ``"dicom-wsi"``, ``"openslide-mirax"`` ...).
        levels: pyramid levels only (:class:`LevelInfo`), finest (level 0) first.
        mpp: micrometres per level-0 pixel when the file says so, else ``None``.
    """

    _handle = None

    # -- context manager -------------------------------------------------
    def __enter__(self) -> SlideReader:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Close the underlying file. Safe to call more than once."""
        if self._handle is not None:
            try:
                self._handle.close()
            finally:
                self._handle = None

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.path!r}, format={self.format!r}, levels={len(self.levels)})"

    # -- geometry --------------------------------------------------------
    @property
    def dimensions(self) -> tuple[int, int]:
        """Level-0 ``(width, height)`` in pixels."""
        return self.levels[0].width, self.levels[0].height

    # -- pixels ----------------------------------------------------------
    def read_level(self, level: int, max_bytes: int = MAX_DECODE_BYTES) -> np.ndarray:
        """Decode a whole level as an ``(height, width, 3)`` ``uint8`` RGB array.

        Refuses (``SlideError``, before decoding anything) when the output would
        need more than ``max_bytes`` bytes (height * width * 3).
        """
        info = self._level(level)
        needed = info.width * info.height * 3
        if needed > max_bytes:
            raise SlideError(
                self.path,
                f"level {level} is {info.width}×{info.height} px = {needed} bytes as RGB, "
                f"over the decode limit of {max_bytes} bytes; read a coarser level or regions",
            )
        return self.read_region(level, 0, 0, info.width, info.height)

    def read_region(self, level: int, x: int, y: int, width: int, height: int) -> np.ndarray:
        """Decode a rectangle of one level as a ``(height, width, 3)`` ``uint8`` RGB array.

        ``x``, ``y`` (top-left corner) and ``width``, ``height`` are in pixels of
        ``level``. Only the tiles (or strips) under the rectangle are read and
        decoded. Parts of the rectangle outside the level are white (255).
        """
        info = self._level(level)
        x, y, width, height = int(x), int(y), int(width), int(height)
        if width < 0 or height < 0:
            raise ValueError(f"region size must be >= 0, got width={width}, height={height}")
        needed = width * height * 3
        if needed > MAX_DECODE_BYTES:
            raise SlideError(
                self.path,
                f"region {width}×{height} px = {needed} bytes as RGB, "
                f"over the decode limit of {MAX_DECODE_BYTES} bytes",
            )
        out = np.full((height, width, 3), 255, dtype=np.uint8)
        # intersection with the level, in level pixels
        x0, y0 = max(x, 0), max(y, 0)
        x1, y1 = min(x + width, info.width), min(y + height, info.height)
        if x0 >= x1 or y0 >= y1:
            return out
        rgb = self._decode_window(level, x0, y0, x1, y1)
        out[y0 - y : y1 - y, x0 - x : x1 - x] = rgb
        return out

    def _level(self, level: int) -> LevelInfo:
        if self._handle is None:
            raise ValueError(f"{self.path}: slide is closed")
        if isinstance(level, bool) or not isinstance(level, (int, np.integer)):
            raise ValueError(f"level must be an int, got {level!r}")
        if not 0 <= level < len(self.levels):
            raise ValueError(f"level {level} out of range: {self.path} has {len(self.levels)} level(s)")
        return self.levels[int(level)]

    def _decode_window(self, level: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """RGB pixels of the in-bounds window [y0:y1, x0:x1] of ``level``: (y1-y0, x1-x0, 3) uint8 (each format's)."""
        raise NotImplementedError


def check_levels(path: str, levels: list[LevelInfo]) -> None:
    """Refuse an inconsistent pyramid: every level must be smaller than the one before it and keep
    level 0's aspect ratio (within 2 % or 2 px of rounding); and stay within the limits every reader shares
    (:mod:`data_tools.slide_files.limits`: sides, level-0 area, level and tile counts)."""
    check_level_sizes(path, levels)
    w0, h0 = levels[0].width, levels[0].height
    for i in range(1, len(levels)):
        prev, lv = levels[i - 1], levels[i]
        if lv.width > prev.width or lv.height > prev.height or (lv.width, lv.height) == (prev.width, prev.height):
            raise SlideError(
                path,
                f"inconsistent pyramid: level {i} is {lv.width}×{lv.height} px, not smaller than "
                f"level {i - 1} ({prev.width}×{prev.height}); rewrite the pyramid or keep only level 0",
            )
        expected_h = lv.width * h0 / w0
        if abs(lv.height - expected_h) > max(2.0, 0.02 * expected_h):
            raise SlideError(
                path,
                f"inconsistent pyramid: level {i} ({lv.width}×{lv.height} px) does not keep the "
                f"aspect ratio of level 0 ({w0}×{h0}); rewrite the pyramid or keep only level 0",
            )


def describe(reader) -> str:
    """Multi-line human-readable summary: file, format, µm/px, one line per level."""
    mpp = "unknown" if reader.mpp is None else f"{reader.mpp:.4g} µm/px (level 0)"
    lines = [
        f"file: {reader.path}",
        f"format: {reader.format}",
        f"mpp: {mpp}",
        f"levels: {len(reader.levels)}",
    ]
    for i, lv in enumerate(reader.levels):
        tiles = "stripped" if lv.tile_size is None else f"tiles {lv.tile_size[0]}×{lv.tile_size[1]}"
        lines.append(
            f"  level {i}: {lv.width}×{lv.height} px, downsample {lv.downsample:.3f}, {tiles}, {lv.compression}"
        )
    associated = getattr(reader, "associated", None)  # OpenSlide's label / macro / thumbnail images
    if associated:
        lines.append("associated images: " + ", ".join(f"{n} {w}×{h} px" for n, (w, h) in associated.items()))
    return "\n".join(lines)
