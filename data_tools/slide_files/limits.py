"""The one set of size limits every slide reader applies (the native TIFF reader, DICOM WSI through wsidicom or
pydicom, OpenSlide), so that a file whose header declares an absurd size is refused in one line naming it before
anything that size is allocated, whichever reader opens it.

Units: pixels of the level concerned; ``MAX_PIXELS`` counts level-0 pixels (width × height).
"""

from __future__ import annotations

from data_tools.errors import SlideError

__all__ = ["MAX_LEVELS", "MAX_PIXELS", "MAX_SIDE", "MAX_TILES", "check_level_sizes", "check_size"]

MAX_SIDE = 1_000_000
"""Largest accepted width or height of any level or tile, in px (the largest scans are ~300,000 px a side)."""

MAX_PIXELS = 250_000_000_000
"""Largest accepted level-0 area, in px (250 gigapixels: a whole 75 × 25 mm slide at 0.12 µm/px is ~130)."""

MAX_LEVELS = 64
"""Most pyramid levels accepted (halving from 1,000,000 px to 1 px takes 20)."""

MAX_TILES = 2**25
"""Most tiles (camera images, DICOM frames) one level may declare: 33,554,432, enough for 250 gigapixels in
tiles of 86 × 86 px."""


def check_size(path, width: int, height: int, what: str = "level 0") -> None:
    """Refuse (:class:`SlideError` naming ``path``) a declared ``width`` × ``height`` px image (``what``: ``"level
    0"``, ``"a tile"`` ...) with a side outside ``1..MAX_SIDE``, or, for level 0, an area over ``MAX_PIXELS``."""
    w, h = int(width), int(height)
    if not (0 < w <= MAX_SIDE and 0 < h <= MAX_SIDE):
        raise SlideError(
            path,
            f"{what} declares {w:,}×{h:,} px, outside the limit of 1..{MAX_SIDE:,} px a side "
            "(corrupt header, or not a slide histojax reads)",
        )
    if what == "level 0" and w * h > MAX_PIXELS:
        raise SlideError(
            path,
            f"level 0 declares {w:,}×{h:,} px = {w * h:,} px, over the limit of {MAX_PIXELS:,} "
            "px (corrupt header, or not a slide histojax reads)",
        )


def check_level_sizes(path, levels) -> None:
    """Refuse a pyramid (``levels``: :class:`data_tools.slide_files.base.LevelInfo`, finest first) with more than
    ``MAX_LEVELS`` levels, a level or tile side outside ``1..MAX_SIDE``, a level-0 area over ``MAX_PIXELS``, or a
    level of more than ``MAX_TILES`` tiles. One :class:`SlideError` line naming ``path``."""
    if not levels:
        raise SlideError(path, "no pyramid level")
    if len(levels) > MAX_LEVELS:
        raise SlideError(path, f"declares {len(levels):,} pyramid levels, over the limit of {MAX_LEVELS}")
    check_size(path, levels[0].width, levels[0].height)
    for k, lv in enumerate(levels):
        check_size(path, lv.width, lv.height, f"level {k}")
        if lv.tile_size is not None:
            tw, th = lv.tile_size
            check_size(path, tw, th, f"level {k}'s tile")
            tiles = -(-int(lv.width) // int(tw)) * -(-int(lv.height) // int(th))
            if tiles > MAX_TILES:
                raise SlideError(
                    path, f"level {k} declares {tiles:,} tiles of {tw}×{th} px, over the limit of {MAX_TILES:,}"
                )
