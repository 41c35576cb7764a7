"""What a navigating episode has seen, and the slide geometry it is counted on (host tables, JAX memory).

The env core's reading tracker: the pan/zoom modes keep it with ``make(..., track_reading=True)`` or
``memory=True`` (``fraction_read`` / ``fields_of_view`` in ``info``, the ``visited`` map in the observation), and
the reading modes of :mod:`histojax.reading` build on it (``zoom_select`` keeps the same memory; ``glimpse`` and the
head reward count the same tissue views).

**Finest-level views** are the non-overlapping ``T × T`` views of the scenario's finest level on a
grid of step ``T`` px: ``gw = (W − T) // T + 1`` columns (likewise rows), view ``(fy, fx)`` with
top-left ``(fx·T, fy·T)``. A view is a **tissue view** when at least ``MIN_START_TISSUE`` (25 %)
of its footprint is tissue in the bundle's tissue mask (a slide with no tissue view at all counts
every view). "Fraction read" is always read tissue views / all tissue views of the slide.

**Seen views** (:class:`SeenTables`, :class:`SeenMemory`): navigating modes (``zoom_select``, and
``discrete`` / ``continuous`` with ``make(..., track_reading=True)`` or ``memory=True``) mark the
view nearest each position on a stride-``T`` grid of its level; a finest-level tissue view seen counts
as read. The observation's ``visited (16, 16)`` is the "coarse visited map": the slide cut into
16 × 16 equal blocks of finest-level views (block ``(fy·16 // gh, fx·16 // gw)``), each holding
the fraction of its tissue views read (0 where it has none).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from histojax.core.slide import MIN_START_TISSUE, summed_area_table

VISITED_MAP = 16  # the coarse visited map is VISITED_MAP × VISITED_MAP blocks of the slide


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
    count = (
        sat[y1[:, None], x1[None, :]]
        - sat[y0[:, None], x1[None, :]]
        - sat[y1[:, None], x0[None, :]]
        + sat[y0[:, None], x0[None, :]]
    )
    area = (y1 - y0)[:, None] * (x1 - x0)[None, :]
    ok = count >= MIN_START_TISSUE * area
    return ok if ok.any() else np.ones_like(ok)


def per_slide(params, bundles):
    """``(single-slide SlideArrays, Bundle)`` of each slide of a (possibly stacked) dataset, one at a time (an
    iterator: each slide's view, with its rows of the start weights, is dropped before the next is made)."""
    slides = params.slide
    return ((slides.select(i), b) for i, b in enumerate(bundles))


def pad_stack(arrays: list[np.ndarray], fill=0) -> np.ndarray:
    """Stack 1-D (or ``(n, …)``) arrays of different lengths, padding the first axis with ``fill``."""
    n = max(a.shape[0] for a in arrays)
    out = np.full((len(arrays), n) + arrays[0].shape[1:], fill, dtype=arrays[0].dtype)
    for i, a in enumerate(arrays):
        out[i, : a.shape[0]] = a
    return out


# ----------------------------------------------------------------------------- seen views (JAX side)
@struct.dataclass
class SeenTables:
    """What a navigating episode can see, per slide of ``S`` (in ``EnvParams.mode_data``); views on
    stride-``T`` grids of every level."""

    grid_offset: jnp.ndarray  # (S, n) int32 first index of level z's grid in the flat ``seen`` array
    grid_width: jnp.ndarray  # (S, n) int32 columns of each level's grid
    grid_height: jnp.ndarray  # (S, n) int32 rows of each level's grid
    tissue: jnp.ndarray  # (S, Vf) bool: finest-level view v is a tissue view (flat, padded False)
    coarse_cell: jnp.ndarray  # (S, Vf) int32 visited-map block of finest view v (padding: Gc, dropped)
    coarse_views: jnp.ndarray  # (S, Gc) float32 tissue views in each block (≥ 1 to divide by), Gc = 16·16
    total_views: jnp.ndarray  # (S,) int32 finest-level tissue views of the slide (≥ 1)
    inv_total: jnp.ndarray  # (S,) float32 1 / total_views
    inv_coarse: jnp.ndarray  # (S, Gc) float32 1 / coarse_views
    read_budget: jnp.ndarray  # () float32 fraction of total_views after which the episode is truncated
    seen_zero: jnp.ndarray  # (⌈V/32⌉,) uint32 all 0: a fresh ``seen`` bit set (V = the largest sum of grid sizes)
    coarse_map: jnp.ndarray | None = None  # (S, 16, 16) float32 coarse map (see coarse_maps below), or None


@struct.dataclass
class SeenMemory:
    """What a navigating episode has seen (in ``EnvState.memory``)."""

    seen: jnp.ndarray  # (⌈V/32⌉,) uint32 bits: view v of every level's grid seen (bit v % 32 of word v // 32)
    views_read: jnp.ndarray  # () int32 finest-level tissue views seen
    fields: jnp.ndarray  # () int32 distinct views seen, any level
    block_read: jnp.ndarray  # (Gc,) int32 finest tissue views read per block of the visited map (Gc = 16·16)


def seen_tables(env, params, bundles, read_budget: float = 1.0) -> SeenTables:
    """The :class:`SeenTables` of a dataset (host side, once)."""
    if not 0.0 < read_budget <= 1.0:
        raise ValueError(f"read_budget must be in (0, 1], got {read_budget}")
    t = env.tile_size
    rows = {k: [] for k in ("offset", "width", "height", "tissue", "coarse", "total")}
    geoms = []
    for slide, bundle in per_slide(params, bundles):
        _, width, height = level_geometry(slide)
        grids = [grid(int(w), int(h), t, t) for w, h in zip(width, height)]
        geoms.append((bundle, grids))
    big_c = VISITED_MAP * VISITED_MAP
    coarse_views = []
    for (slide, _), (bundle, grids) in zip(per_slide(params, bundles), geoms):
        sizes = [h * w for h, w in grids]
        rows["offset"].append(np.cumsum([0] + sizes[:-1]).astype(np.int32))
        rows["width"].append(np.asarray([w for _, w in grids], np.int32))
        rows["height"].append(np.asarray([h for h, _ in grids], np.int32))
        tissue = tissue_views(bundle, slide, t).reshape(-1)
        gh, gw = grids[-1]
        fy, fx = np.divmod(np.arange(gh * gw), gw)
        coarse = (fy * VISITED_MAP // gh) * VISITED_MAP + fx * VISITED_MAP // gw
        counts = np.bincount(coarse[tissue], minlength=big_c).astype(np.float32)
        coarse_views.append(np.maximum(counts, 1.0))
        rows["tissue"].append(tissue)
        rows["coarse"].append(coarse.astype(np.int32))
        rows["total"].append(max(1, int(tissue.sum())))
    return SeenTables(
        grid_offset=jnp.asarray(np.stack(rows["offset"])),
        grid_width=jnp.asarray(np.stack(rows["width"])),
        grid_height=jnp.asarray(np.stack(rows["height"])),
        tissue=jnp.asarray(pad_stack(rows["tissue"], False)),
        coarse_cell=jnp.asarray(pad_stack(rows["coarse"], big_c)),
        coarse_views=jnp.asarray(np.stack(coarse_views)),
        total_views=jnp.asarray(rows["total"], jnp.int32),
        inv_total=jnp.asarray(1.0 / np.asarray(rows["total"], np.float64), jnp.float32),
        inv_coarse=jnp.asarray(1.0 / np.stack(coarse_views).astype(np.float64), jnp.float32),
        read_budget=jnp.float32(read_budget),
        seen_zero=jnp.zeros(
            (
                seen_words(
                    max(
                        int(o[-1]) + int(w[-1]) * int(h[-1])
                        for o, w, h in zip(rows["offset"], rows["width"], rows["height"])
                    )
                ),
            ),
            jnp.uint32,
        ),
    )


def seen_words(views: int) -> int:
    """uint32 words of a ``seen`` bit set of ``views`` views (≥ 1)."""
    return max(1, (int(views) + 31) // 32)


def seen_flags(words, start: int, size: int) -> np.ndarray:
    """Host: ``(size,)`` bool, views ``start .. start + size - 1`` of a ``seen`` bit set ``words``
    (``(⌈V/32⌉,)`` uint32, e.g. one env's ``memory.seen``)."""
    bits = np.unpackbits(np.asarray(words).astype("<u4").view(np.uint8), bitorder="little").astype(bool)
    return bits[start : start + size]


def init_seen(tables: SeenTables, state, env) -> SeenMemory:
    """A fresh :class:`SeenMemory` that has seen the start view of ``state``."""
    zero = jnp.zeros((), jnp.int32)
    return see(
        tables,
        SeenMemory(seen=tables.seen_zero, views_read=zero, fields=zero, block_read=block_zero(tables)),
        state.slide_index,
        state.z,
        state.x,
        state.y,
        env,
    )


def block_zero(tables: SeenTables) -> jax.Array:
    """A fresh ``block_read``: zeros ``(Gc,)`` int32."""
    return jnp.zeros(tables.coarse_views.shape[-1:], jnp.int32)


def _grid_index(tables: SeenTables, i, z, x, y, tile_size: int):
    """Flat index in ``seen`` of the stride-``T`` grid view nearest ``(z, x, y)``, and its index in
    level ``z``'s grid."""
    gw, gh = tables.grid_width[i, z], tables.grid_height[i, z]
    gx = jnp.clip((x + tile_size // 2) // tile_size, 0, gw - 1)
    gy = jnp.clip((y + tile_size // 2) // tile_size, 0, gh - 1)
    return tables.grid_offset[i, z] + gy * gw + gx, gy * gw + gx


def see(tables: SeenTables, memory, i, z, x, y, env):
    """``memory`` (any dataclass with ``seen``, ``views_read``, ``fields``, ``block_read``, or the
    episode-stamped ``words`` / ``stamp`` / ``block_raw`` / ``block_stamp`` / ``episode`` of
    :class:`histojax.reading.modes.zoom_select.ZoomMemory`) after looking at ``(z, x, y)`` of slide ``i``: the view is
    marked and counted once; a finest tissue view read adds 1 to its block of the visited map (updated
    here, never recounted). One word and one block are read and written."""
    index, local = _grid_index(tables, i, z, x, y, env.tile_size)
    word = index // 32
    bit = jnp.left_shift(jnp.uint32(1), (index % 32).astype(jnp.uint32))
    stamped = getattr(memory, "episode", None) is not None
    if stamped:  # a word written in an earlier episode reads as 0
        word_stamp = memory.stamp[word]
        bits = jnp.where(word_stamp == memory.episode, memory.words[word], jnp.uint32(0))
    else:
        bits = memory.seen[word]
    new = (bits & bit) == 0
    finest = z == env.n_levels - 1
    view = jnp.clip(local, 0, tables.tissue.shape[-1] - 1)
    read = new & finest & tables.tissue[i, view]
    counts = dict(views_read=memory.views_read + read.astype(jnp.int32), fields=memory.fields + new.astype(jnp.int32))
    block = tables.coarse_cell[i, view]  # Gc (dropped) for padding, which is never read
    if not stamped:
        return memory.replace(
            seen=memory.seen.at[word].set(bits | bit),
            **counts,
            block_read=memory.block_read.at[block].add(read.astype(jnp.int32), mode="drop"),
        )
    b = jnp.minimum(block, memory.block_raw.shape[-1] - 1)
    block_stamp = memory.block_stamp[b]
    held = jnp.where(block_stamp == memory.episode, memory.block_raw[b], 0)
    # stamps never exceed ``episode``, so the max is ``episode``; written from the value read, it makes XLA read
    # before it writes and update the stamps in place (a constant write let it copy the whole array first)
    return memory.replace(
        words=memory.words.at[word].set(bits | bit),
        stamp=memory.stamp.at[word].set(jnp.maximum(word_stamp, memory.episode)),
        block_raw=memory.block_raw.at[block].set(held + read.astype(jnp.int32), mode="drop"),
        block_stamp=memory.block_stamp.at[block].set(jnp.maximum(block_stamp, memory.episode), mode="drop"),
        **counts,
    )


def budget_spent(tables, memory, i) -> jax.Array:
    """True once the finest tissue views read reach ``read_budget`` (never with a budget of 1)."""
    fraction = memory.views_read.astype(jnp.float32) * tables.inv_total[i]
    return (tables.read_budget < 1.0) & (fraction >= tables.read_budget)


def reading_info(tables, memory, i) -> dict:
    """``fraction_read`` (float32) and ``fields_of_view`` (int32) for ``info``."""
    return {
        "fraction_read": memory.views_read.astype(jnp.float32) * tables.inv_total[i],
        "fields_of_view": memory.fields,
    }


def visited_obs(env, state, params) -> dict:
    """``visited (16, 16)`` float32 (the coarse visited map, see the module doc) and ``position (3,)``."""
    tables, i = params.mode_data, state.slide_index
    per_cell = state.memory.block_read.astype(jnp.float32)  # kept up to date by see(): 256 numbers, no recount
    return {
        "visited": (per_cell * tables.inv_coarse[i]).reshape(VISITED_MAP, VISITED_MAP),
        "position": env._position(state, params.slide.select(i)),
    }


def visited_space(params) -> dict:
    """Spaces of :func:`visited_obs`."""
    from histojax.core import spaces

    return {
        "visited": spaces.Box(0.0, 1.0, (VISITED_MAP, VISITED_MAP), jnp.float32),
        "position": spaces.Box(0.0, 1.0, (3,), jnp.float32),
    }


def with_tracking(env, params):
    """``(env, params)`` whose episodes report ``fraction_read`` and ``fields_of_view`` in ``info``
    (unchanged when they already do; trajectories stay the same): the pan/zoom modes get their
    :class:`SeenTables` as ``make(..., track_reading=True)`` would give them."""
    import dataclasses

    if params.mode_data is not None:
        return env, params
    params = params.replace(mode_data=env.action.prepare(env, params, env.bundles, track_reading=True))
    return dataclasses.replace(env, _default_params=params), params


# ----------------------------------------------------------------------------- the coarse map's builder (a plug)
_COARSE_MAP_BUILDER: list = []  # the one builder registered (the reading stack's, when histojax is imported)


def register_coarse_map(build) -> None:
    """Plug in the builder of a ``discrete:map`` / ``continuous:map`` navigator's coarse map: ``build(env, params,
    bundles, feature, level, head=None)`` → ``(S, 16, 16)`` float32 (one map per slide, host side, once in
    ``make``). The reading stack registers :func:`histojax.reading.coarse_map.coarse_maps` when it is imported
    (``import histojax`` imports it), so the env core calls it without importing ``histojax.reading``."""
    _COARSE_MAP_BUILDER[:] = [build]


def coarse_maps(env, params, bundles, feature, level: int = -3, head=None) -> np.ndarray:
    """``(S, 16, 16)`` float32: the coarse map of every slide, by the builder :func:`register_coarse_map` plugged in
    (``ValueError``, one line, when none is)."""
    if not _COARSE_MAP_BUILDER:
        raise ValueError(
            "a coarse map (action_mode discrete:map / continuous:map) is built by the reading stack: "
            "import histojax (it registers histojax.reading.coarse_map.coarse_maps)"
        )
    return _COARSE_MAP_BUILDER[0](env, params, bundles, feature, level, head=head)
