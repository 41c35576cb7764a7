"""``SlideArrays``: the device arrays of one slide for one scenario, and the pure array helpers that build its
start weights (no file is read here: loading a bundle onto the device is :mod:`histojax.loading`).

All levels are packed into flat arrays with per-level offsets, so the view at any
level is one gather whatever ``z`` is (no ``lax.switch`` over levels):
  * ``pixels``  — ``(P, 3)`` uint8, level ``z`` row-major from ``level_offset[z]`` with row
    stride ``level_width[z]``;
  * ``tumour_sat`` — uint32 summed-area table of the 0/1 tumour mask of each level, kept
    modulo 2**32: a box sum ``S[d] - S[b] - S[c] + S[a]`` in wrapping uint32 arithmetic is
    exact whenever the box holds fewer than 2**32 px (a view holds T² px), however large the
    level — no overflow by construction;
    ``(H+1) × (W+1)`` per level, row-major from ``sat_offset[z]``;
  * ``start_logits`` — ``(Hc - T + 1, Wc - T + 1)`` float32 log-weights of start
    positions (top-left corner, px of the coarsest level).
Level ``z = 0`` is the coarsest, ``z = n_levels - 1`` the finest.

A *tiled* slide (a bundle built with ``storage="tiled"``, for gigapixel slides) has ``pixels`` and
``tumour_sat`` ``None`` and instead:
  * ``tile_pool`` — ``(N, T, T, 3)`` uint8 RGB tiles of all levels (each level's tile 0 is blank white,
    shared by its background tiles; pool tile 0 is uniform and the last tile is a spare blank one,
    which the view's row slices rely on, see :func:`histojax.core.views.view_pixels`);
  * ``tile_index`` — ``(G,)`` int32, level ``z``'s ``gh × gw`` grid of pool indices row-major from
    ``tile_offset[z]`` with ``gw = tile_grid_width[z]``;
  * ``sat_pool`` — ``(M, T+1, T+1)`` uint32 local summed-area tables of each tile's tumour mask, and
    ``sat_index`` ``(G,)`` int32 laid out like ``tile_index``.
A view then covers at most 2 × 2 tiles (see :mod:`histojax.core.views`).

**Feature-only layout** (:func:`histojax.loading.load_slide` with ``pixels=False``, what ``make`` does for
``obs_mode="features"``): no pixels reach the device at all — ``pixels`` and ``tile_pool`` / ``tile_index`` are
``None``; only the tumour tables (``tumour_sat``, or ``sat_pool`` / ``sat_index`` with the grid geometry), the start
weights and the feature grid are there.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

MIN_START_TISSUE = 0.25  # a random start view holds at least this tissue fraction (when any view does)


@struct.dataclass
class SlideArrays:
    """Device arrays of one slide at the ``n_levels`` zoom levels of a scenario (see module doc)."""

    pixels: jnp.ndarray | None  # (P, 3) uint8; None for a tiled slide
    level_offset: jnp.ndarray  # (n,) int32, first pixel row of each level in ``pixels``
    level_width: jnp.ndarray  # (n,) int32, px
    level_height: jnp.ndarray  # (n,) int32, px
    downsample: jnp.ndarray  # (n,) float32, level-0 px per px of the level
    tumour_sat: jnp.ndarray | None  # (S,) uint32, modulo 2**32; None for a tiled slide
    sat_offset: jnp.ndarray  # (n,) int32
    start_logits: jnp.ndarray  # (Hc - T + 1, Wc - T + 1) float32
    # optional feature grid (``obs_mode="features"``; ``None`` when not loaded), see ``view_features``:
    features: jnp.ndarray | None = None  # (F, D) float16/float32, level z's grid row-major from feature_offset[z]
    feature_offset: jnp.ndarray | None = None  # (n,) int32, first row of each level in ``features``
    feature_grid_width: jnp.ndarray | None = None  # (n,) int32, grid columns gw of each level
    feature_grid_height: jnp.ndarray | None = None  # (n,) int32, grid rows gh of each level
    feature_stride: jnp.ndarray | None = None  # () int32, px of a level between grid positions
    # slide-level data; for a dataset of S slides (:func:`histojax.loading.stack_slides`) every per-level array above
    # gets a leading axis S (``(S, n)``, start_logits ``(S, Hmax, Wmax)``, feature_stride ``(S,)``):
    slide_label: jnp.ndarray | None = None  # () or (S,) int32: 1 tumour, 0 no tumour (classification)
    slide_logits: jnp.ndarray | None = None  # (S,) float32 log-weights of sampling each slide at reset
    # tiled slides (``pixels`` / ``tumour_sat`` None), see the module doc:
    tile_pool: jnp.ndarray | None = None  # (N, T, T, 3) uint8
    tile_index: jnp.ndarray | None = None  # (G,) int32 pool index per grid cell, all levels
    tile_offset: jnp.ndarray | None = None  # (n,) int32 first grid cell of each level in tile_index / sat_index
    tile_grid_width: jnp.ndarray | None = None  # (n,) int32 grid columns gw of each level
    sat_pool: jnp.ndarray | None = None  # (M, T+1, T+1) uint32 local summed-area tables
    sat_index: jnp.ndarray | None = None  # (G,) int32 SAT pool index per grid cell
    # derived once by ``make`` (:func:`start_cdf`), so a reset does not redo it over the whole coarsest level:
    start_cdf: jnp.ndarray | None = (
        None  # (Hc'·Wc',) or (S, Hmax·Wmax) float32 cumulative start weights; None: per reset
    )

    @property
    def is_tiled(self) -> bool:
        """True for a tiled slide (a static Python bool); also without pixels (feature-only layout)."""
        return self.sat_pool is not None

    @property
    def has_pixels(self) -> bool:
        """False in the feature-only layout (a static Python bool)."""
        return self.pixels is not None or self.tile_pool is not None

    @property
    def num_slides(self) -> int:
        """1 for one slide, S for a stacked dataset (a static Python int)."""
        return 1 if self.level_width.ndim == 1 else int(self.level_width.shape[0])

    def select(self, index) -> "SlideArrays":
        """The single-slide view of slide ``index`` (a traced int32 is fine): per-level arrays
        ``(n,)``, ``start_logits`` 2-D; the shared flat arrays are returned as they are (their
        offsets are absolute). For one slide, ``self`` unchanged."""
        if self.level_width.ndim == 1:
            return self
        pick = lambda a: None if a is None else a[index]  # noqa: E731
        return self.replace(
            level_offset=pick(self.level_offset),
            level_width=pick(self.level_width),
            level_height=pick(self.level_height),
            downsample=pick(self.downsample),
            sat_offset=pick(self.sat_offset),
            start_logits=pick(self.start_logits),
            start_cdf=pick(self.start_cdf),
            feature_offset=pick(self.feature_offset),
            feature_grid_width=pick(self.feature_grid_width),
            feature_grid_height=pick(self.feature_grid_height),
            feature_stride=pick(self.feature_stride),
            slide_label=pick(self.slide_label),
            tile_offset=pick(self.tile_offset),
            tile_grid_width=pick(self.tile_grid_width),
        )


def summed_area_table(mask: np.ndarray) -> np.ndarray:
    """Integral image ``S`` of a 2-D 0/1 mask with a zero first row and column: ``(H+1, W+1)`` int64,
    ``S[i, j]`` = number of mask pixels in rows ``< i`` and columns ``< j``."""
    sat = np.zeros((mask.shape[0] + 1, mask.shape[1] + 1), dtype=np.int64)
    np.cumsum(np.cumsum(mask, axis=0, dtype=np.int64), axis=1, out=sat[1:, 1:])
    return sat


def box_sums(sat: np.ndarray, size: int) -> np.ndarray:
    """Sums of every ``size × size`` window of the mask behind ``sat``: ``(H-size+1, W-size+1)``."""
    return sat[size:, size:] - sat[:-size, size:] - sat[size:, :-size] + sat[:-size, :-size]


def start_cdf(logits) -> np.ndarray:
    """The cumulative start weights ``cumsum(exp(logits − max))`` over the flattened start positions (per
    slide for stacked ``(S, H, W)`` logits), float32: exactly what :func:`histojax.core.env.sample_index`
    would compute from the logits at every reset (start weights are 1 or 0, so the sums are exact
    integers), computed once on the host instead (the auto-reset runs in every step, and on a
    true-scale slide the coarsest level has ~500,000 start positions)."""
    logits = np.asarray(logits, np.float32)
    flat = logits.reshape(logits.shape[:-2] + (-1,))
    weights = np.exp(flat - flat.max(axis=-1, keepdims=True))
    return np.cumsum(weights, axis=-1, dtype=np.float32)


def start_logits(tissue: np.ndarray, tile_size: int, region: np.ndarray | None = None) -> np.ndarray:
    """Log-weights of start views at the coarsest level: 0 where the view's tissue fraction is at
    least ``MIN_START_TISSUE`` (or, if no view reaches it, where it is maximal), ``-inf`` elsewhere.
    A slide with no tissue detected at all gets uniform starts. ``region`` (a region bundle's mask
    at the coarsest level) further requires the view's centre pixel inside it."""
    frac = box_sums(summed_area_table(tissue.astype(np.uint8)), tile_size) / float(tile_size * tile_size)
    if frac.max() <= 0:
        ok = np.ones_like(frac, dtype=bool)
    else:
        ok = frac >= min(MIN_START_TISSUE, frac.max())
    if region is not None:
        c = tile_size // 2
        centre = np.asarray(region, dtype=bool)[c : c + frac.shape[0], c : c + frac.shape[1]]
        if (ok & centre).any():
            ok = ok & centre
        elif centre.any():
            ok = centre
    return np.where(ok, 0.0, -np.inf).astype(np.float32)
