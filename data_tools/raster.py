"""Raster helpers shared by the dense and tiled bundle writers: area resampling and padding.

(Their own module so :mod:`data_tools.bundle` and :mod:`data_tools.tiled` both import them without
importing each other.)
"""

from __future__ import annotations

import math

import numpy as np
from PIL import Image


def resample(
    source: np.ndarray,
    source_downsample: float,
    downsample: float,
    size: tuple[int, int],
    offset: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """Area-average ``source`` (a level at ``source_downsample``) to a level at ``downsample`` of ``size`` (W, H);
    ``offset`` is where the output's top-left corner lies in ``source`` (px of the source). Returns uint8."""
    scale = downsample / source_downsample
    width, height = size
    ox, oy = offset
    if (
        math.isclose(scale, 1.0)
        and ox == int(ox)
        and oy == int(oy)
        and source.shape[1] >= width + ox
        and source.shape[0] >= height + oy
    ):
        return np.ascontiguousarray(source[int(oy) : int(oy) + height, int(ox) : int(ox) + width])
    box = (ox, oy, min(ox + width * scale, source.shape[1]), min(oy + height * scale, source.shape[0]))
    image = Image.fromarray(source).resize((width, height), resample=Image.Resampling.BOX, box=box)
    return np.asarray(image, dtype=np.uint8)


def pad(array: np.ndarray, min_side: int, fill: int) -> np.ndarray:
    """Pad at the bottom/right so both sides are at least ``min_side`` px (a view must fit)."""
    h, w = array.shape[:2]
    ph, pw = max(0, min_side - h), max(0, min_side - w)
    if ph == 0 and pw == 0:
        return array
    widths = ((0, ph), (0, pw)) + ((0, 0),) * (array.ndim - 2)
    return np.pad(array, widths, constant_values=fill)


__all__ = ["pad", "resample"]
