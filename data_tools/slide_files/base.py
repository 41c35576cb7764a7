"""What every slide-file reader shares: the description of a pyramid level (:class:`LevelInfo`), the pyramid checks
every reader applies to the levels a file declares (:func:`check_levels`) and the human-readable summary
``data_tools info`` prints (:func:`describe`).

The readers themselves: :mod:`data_tools.slide_files.tiff` (SVS, pyramidal TIFF, OME-TIFF: the class
:class:`~data_tools.slide_files.tiff.SlideReader` whose interface the others keep), :mod:`data_tools.slide_files.dicom`
(DICOM WSI) and :mod:`data_tools.slide_files.openslide` (the formats OpenSlide reads); :func:`data_tools.slide_files.open.open_slide`
picks one. Units: pixels of the level concerned; ``downsample`` in level-0 px per level px.
"""

from __future__ import annotations

from dataclasses import dataclass

from data_tools.errors import SlideError
from data_tools.slide_files.limits import check_level_sizes

__all__ = ["LevelInfo", "check_levels", "describe"]


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
