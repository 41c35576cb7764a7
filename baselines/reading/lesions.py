"""CAMELYON lesion classes of a tumour annotation (a leaf module: shapely geometry in, class out) and of a slide
(:func:`lesion_class`), used by the readers' lesion table, the learned head's fit and ``evaluate``'s per-lesion
rows."""
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


CLASSES = ("ITC", "micro", "macro")


def lesion_class(slide: dict) -> tuple[str, float]:
    """``(class, largest lesion's longest diameter in mm)`` of a slide: ``"normal"`` for a label-0 slide,
    else ``ITC`` / ``micro`` / ``macro`` by CAMELYON's thresholds (0.2 and 2 mm). Lesions are the connected
    pieces of the tumour annotation; a tumour slide without polygons is ``"unknown"``."""
    if not slide["label"]:
        return "normal", 0.0
    return lesion_of(slide.get("tumour"), slide["mpp"])
