"""What a slide offers to read, on the host: its finest-level views, which hold tissue, and which
cell of a coarser grid each lies under. Shared by the reading modes (``glimpse``, ``zoom_select``).

**Finest-level views** are the non-overlapping ``T × T`` views of the scenario's finest level on a
grid of step ``T`` px: ``gw = (W − T) // T + 1`` columns (likewise rows), view ``(fy, fx)`` with
top-left ``(fx·T, fy·T)``. A view is a **tissue view** when at least ``MIN_START_TISSUE`` (25 %)
of its footprint is tissue in the bundle's tissue mask (a slide with no tissue view at all counts
every view). "Fraction read" is always read tissue views / all tissue views of the slide.

A **cell grid** at level ``g`` with step ``s`` px puts each finest view under exactly one cell, the
one holding the view's centre (``gx = clip(floor(cx_g / s), 0, gw_g − 1)``, ``cx_g`` the centre in px
of level ``g``): a partition, so reading every cell reads every view once.
"""
from __future__ import annotations

import numpy as np

from histojax.slide import MIN_START_TISSUE, summed_area_table


def grid(width: int, height: int, step: int, tile_size: int) -> tuple[int, int]:
    """``(gh, gw)``: positions of ``tile_size`` views at a step of ``step`` px inside a level (≥ 1 each)."""
    return max(1, (height - tile_size) // step + 1), max(1, (width - tile_size) // step + 1)


def level_geometry(slide) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Host copies of one slide's ``(downsample, width, height)`` per scenario level."""
    return np.asarray(slide.downsample, np.float64), np.asarray(slide.level_width), np.asarray(slide.level_height)


def tissue_views(bundle, slide, tile_size: int) -> np.ndarray:
    """``(gh, gw)`` bool: the finest-level views holding ≥ 25 % tissue (see the module doc)."""
    ds, width, height = level_geometry(slide)
    f = len(ds) - 1
    gh, gw = grid(int(width[f]), int(height[f]), tile_size, tile_size)
    tissue = np.asarray(bundle.tissue, bool)
    th, tw = tissue.shape
    scale = tw / float(width[f])  # tissue-mask px per px of the finest level (the mask spans the slide)
    sat = summed_area_table(tissue.astype(np.uint8)).astype(np.int64)

    def edges(n):
        a = np.floor(np.arange(n) * tile_size * scale).astype(np.int64)
        b = np.maximum(a + 1, np.ceil((np.arange(n) + 1) * tile_size * scale).astype(np.int64))
        return a, b

    x0, x1 = edges(gw)
    y0, y1 = edges(gh)
    x0, x1 = np.clip(x0, 0, tw - 1), np.clip(x1, 1, tw)
    y0, y1 = np.clip(y0, 0, th - 1), np.clip(y1, 1, th)
    count = (sat[y1[:, None], x1[None, :]] - sat[y0[:, None], x1[None, :]]
             - sat[y1[:, None], x0[None, :]] + sat[y0[:, None], x0[None, :]])
    area = (y1 - y0)[:, None] * (x1 - x0)[None, :]
    ok = count >= MIN_START_TISSUE * area
    return ok if ok.any() else np.ones_like(ok)


def cell_of_views(slide, tile_size: int, level: int, step: int, cell_grid: tuple[int, int]) -> np.ndarray:
    """``(gh, gw)`` int64: for each finest-level view, the index ``gy·gw_g + gx`` of the cell of
    ``cell_grid = (gh_g, gw_g)`` at ``level`` (step ``step`` px) holding its centre."""
    ds, width, height = level_geometry(slide)
    f = len(ds) - 1
    gh, gw = grid(int(width[f]), int(height[f]), tile_size, tile_size)
    ratio = ds[f] / ds[level]  # px of level g per px of the finest level
    cx = ((np.arange(gw) + 0.5) * tile_size * ratio) // step
    cy = ((np.arange(gh) + 0.5) * tile_size * ratio) // step
    gx = np.clip(cx, 0, cell_grid[1] - 1).astype(np.int64)
    gy = np.clip(cy, 0, cell_grid[0] - 1).astype(np.int64)
    return gy[:, None] * cell_grid[1] + gx[None, :]


def finest_view_features(slide, tile_size: int) -> np.ndarray:
    """``(gh, gw, D)`` float32 features of the finest-level views: the feature-grid row nearest
    each view's top-left corner, as :func:`histojax.modes.view_features` reads it."""
    ds, width, height = level_geometry(slide)
    f = len(ds) - 1
    gh, gw = grid(int(width[f]), int(height[f]), tile_size, tile_size)
    s = int(np.asarray(slide.feature_stride))
    fgw, fgh = int(np.asarray(slide.feature_grid_width)[f]), int(np.asarray(slide.feature_grid_height)[f])
    x = np.arange(gw) * tile_size
    y = np.arange(gh) * tile_size
    fx = np.clip((x + s // 2) // s, 0, fgw - 1)
    fy = np.clip((y + s // 2) // s, 0, fgh - 1)
    rows = int(np.asarray(slide.feature_offset)[f]) + fy[:, None] * fgw + fx[None, :]
    return np.asarray(slide.features, np.float32)[rows]


def per_slide(params, bundles):
    """``[(single-slide SlideArrays, Bundle), ...]`` of a (possibly stacked) dataset."""
    slides = params.slide
    return [(slides.select(i), b) for i, b in enumerate(bundles)]


def pad_stack(arrays: list[np.ndarray], fill=0) -> np.ndarray:
    """Stack 1-D (or ``(n, …)``) arrays of different lengths, padding the first axis with ``fill``."""
    n = max(a.shape[0] for a in arrays)
    out = np.full((len(arrays), n) + arrays[0].shape[1:], fill, dtype=arrays[0].dtype)
    for i, a in enumerate(arrays):
        out[i, : a.shape[0]] = a
    return out
