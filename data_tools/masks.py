"""Rasterising annotation geometry and detecting tissue, at one pyramid level.

Pixel convention: pixel (row i, column j) of a level with downsample ``d`` covers
level-0 pixels ``[j*d, (j+1)*d) × [i*d, (i+1)*d)``; it counts as inside a polygon
when its centre ``((j+0.5)*d, (i+0.5)*d)`` (level-0 px) lies inside.
"""

from __future__ import annotations

import numpy as np
import shapely
from skimage.color import rgb2hsv
from skimage.filters import threshold_otsu

CHUNK_POINTS = 1 << 22  # pixel centres tested per call: bounds the temporary memory (~100 MB)


def rasterize(geometry, width: int, height: int, downsample: float) -> np.ndarray:
    """Rasterise polygons given in level-0 px onto a level of ``width × height`` px.

    ``geometry`` is a shapely Polygon or MultiPolygon (holes are respected);
    ``downsample`` is level-0 px per px of the target level. Returns a
    ``(height, width)`` bool array, True where the pixel centre is strictly inside.
    Uses shapely's vectorised ``contains_xy`` on a prepared geometry (no hand-written
    scan line), one polygon's bounding box at a time, in row chunks of bounded size.
    """
    mask = np.zeros((height, width), dtype=bool)
    if geometry is None or geometry.is_empty:
        return mask
    for poly in shapely.get_parts(geometry):
        if poly.geom_type != "Polygon" or poly.is_empty:
            continue
        minx, miny, maxx, maxy = poly.bounds
        c0, c1 = max(0, int(np.floor(minx / downsample - 0.5))), min(width, int(np.ceil(maxx / downsample + 0.5)))
        r0, r1 = max(0, int(np.floor(miny / downsample - 0.5))), min(height, int(np.ceil(maxy / downsample + 0.5)))
        if c0 >= c1 or r0 >= r1:
            continue
        shapely.prepare(poly)
        xs = (np.arange(c0, c1) + 0.5) * downsample
        rows_per_chunk = max(1, CHUNK_POINTS // (c1 - c0))
        for top in range(r0, r1, rows_per_chunk):
            bottom = min(r1, top + rows_per_chunk)
            ys = (np.arange(top, bottom) + 0.5) * downsample
            inside = shapely.contains_xy(poly, xs[None, :], ys[:, None])
            mask[top:bottom, c0:c1] |= inside
    return mask


def tissue_mask(rgb: np.ndarray) -> np.ndarray:
    """Tissue vs glass on an RGB uint8 image ``(H, W, 3)``: Otsu threshold on HSV saturation.

    Returns a ``(H, W)`` bool array. A uniform image (no threshold exists) is all
    background. Meant for a coarse level (a few hundred pixels a side).
    """
    saturation = rgb2hsv(rgb[..., :3])[..., 1]
    if float(saturation.max() - saturation.min()) < 1e-6:
        return np.zeros(saturation.shape, dtype=bool)
    threshold = threshold_otsu(saturation)
    # Glass has near-zero saturation; guard against Otsu splitting two shades of glass.
    return saturation > max(threshold, 0.05)
