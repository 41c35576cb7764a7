"""CAMELYON lesion classes of a tumour annotation (a leaf module: shapely geometry in, class out), used by the
readers' lesion table and by ``evaluate``'s per-lesion rows."""
from __future__ import annotations

import numpy as np

ITC_MM, MACRO_MM = 0.2, 2.0   # CAMELYON's thresholds: isolated tumour cells below 0.2 mm, macro-metastases above 2 mm


def longest_diameter_px(geom) -> float:
    """The longest distance between two points of a polygon (px): the diameter of its convex hull."""
    hull = np.asarray(geom.convex_hull.exterior.coords if geom.convex_hull.geom_type == "Polygon"
                      else geom.convex_hull.coords, np.float64)
    if len(hull) < 2:
        return 0.0
    d = hull[:, None, :] - hull[None, :, :]
    return float(np.sqrt((d ** 2).sum(-1)).max())


def lesion_of(geom, mpp: float) -> tuple[str, float]:
    """``(class, mm)`` of a tumour geometry in px at ``mpp`` µm/px: its largest connected piece's longest
    diameter, ``ITC`` below 0.2 mm, ``micro`` up to 2 mm, ``macro`` above; ``"unknown"`` when empty."""
    if geom is None or geom.is_empty:
        return "unknown", float("nan")
    parts = list(getattr(geom, "geoms", [geom]))
    mm = max(longest_diameter_px(p) for p in parts) * mpp / 1000.0
    return ("ITC" if mm < ITC_MM else "micro" if mm <= MACRO_MM else "macro"), mm
