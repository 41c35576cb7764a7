"""Rasterising annotation geometry and detecting tissue, at one pyramid level.

Pixel convention: pixel (row i, column j) of a level with downsample ``d`` covers
level-0 pixels ``[j*d, (j+1)*d) × [i*d, (i+1)*d)``; it counts as inside a polygon
when its centre ``((j+0.5)*d, (i+0.5)*d)`` (level-0 px) lies inside.
"""
from __future__ import annotations

import numpy as np
import shapely
from skimage.color import rgb2hsv
from skimage.draw import polygon as fill_polygon
from skimage.filters import threshold_otsu


def _fill_ring(mask: np.ndarray, ring, downsample: float, value: bool) -> None:
    coords = np.asarray(ring.coords, dtype=np.float64)
    cols = coords[:, 0] / downsample - 0.5
    rows = coords[:, 1] / downsample - 0.5
    rr, cc = fill_polygon(rows, cols, shape=mask.shape)
    mask[rr, cc] = value


def rasterize(geometry, width: int, height: int, downsample: float) -> np.ndarray:
    """Rasterise polygons given in level-0 px onto a level of ``width × height`` px.

    ``geometry`` is a shapely Polygon or MultiPolygon (holes are respected);
    ``downsample`` is level-0 px per px of the target level. Returns a
    ``(height, width)`` bool array, True where the pixel centre is inside.
    Uses scikit-image's polygon fill (pixel-centre rule), not a hand-written scan line.
    """
    mask = np.zeros((height, width), dtype=bool)
    if geometry is None or geometry.is_empty:
        return mask
    for poly in shapely.get_parts(geometry):
        if poly.geom_type != "Polygon" or poly.is_empty:
            continue
        part = np.zeros_like(mask)
        _fill_ring(part, poly.exterior, downsample, True)
        for hole in poly.interiors:
            _fill_ring(part, hole, downsample, False)
        mask |= part
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
