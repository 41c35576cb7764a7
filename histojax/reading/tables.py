"""The reading modes' per-slide tables on the host: which cell of a coarser grid each finest-level view lies
under, and the views' feature vectors. Shared by ``glimpse`` (:mod:`histojax.reading.modes.glimpse`) and the head
reward (:mod:`histojax.reading.head_reward`); the finest-level views, tissue views and the seen-views memory they
count on are the env core's (:mod:`histojax.core.seen_views`).

A **cell grid** at level ``g`` with step ``s`` px puts each finest view under exactly one cell, the
one holding the view's centre (``gx = clip(floor(cx_g / s), 0, gw_g − 1)``, ``cx_g`` the centre in px
of level ``g``): a partition, so reading every cell reads every view once.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from histojax.core.seen_views import grid, level_geometry


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


def feature_rows(slide, rows: np.ndarray) -> np.ndarray:
    """Host float32 copy of rows ``rows`` (any shape of absolute row indices) of ``slide.features``:
    gathered where the bank lives and only those rows copied, never the whole (stacked) bank."""
    rows = np.asarray(rows)
    flat = rows.reshape(-1)
    # padded to a power of two: one compiled gather per size class, not one per slide (each compiled
    # program stays in memory: hundreds of them held GBs of host memory for a full dataset)
    padded = np.zeros(1 << max(0, int(flat.size - 1).bit_length()), np.int32)
    padded[: flat.size] = flat
    picked = np.asarray(jnp.take(slide.features, jnp.asarray(padded), axis=0)[: flat.size], np.float32)
    return picked.reshape(*rows.shape, -1)


def finest_view_features(slide, tile_size: int) -> np.ndarray:
    """``(gh, gw, D)`` float32 features of the finest-level views: the feature-grid row nearest
    each view's top-left corner, as :func:`histojax.core.modes.base.view_features` reads it."""
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
    return feature_rows(slide, rows)
