"""``action_mode="zoom_select"`` (RLogist style): at level ``z`` the view's footprint at level
``z + 1`` is split into ``k × k`` children; action ``i < k²`` zooms into child ``i`` (row-major:
``i = row·k + col``); action ``k²`` zooms out to the parent view (the view this one was
zoomed into from; at the coarsest level it stays); for ``task="classification"`` ``k² + 1`` declares no tumour and ``k² + 2`` tumour.

Child ``(row, col)`` is the ``T × T`` view of level ``z + 1`` centred on the centre of the
footprint's sub-square ``(row, col)`` (footprint side ``T · ratio`` px of level ``z + 1``,
``ratio`` the zoom factor between the levels), clamped inside the level. With ``k`` equal to the
zoom factor (2 for histojax's bundles, the default) the children tile the footprint exactly. At the
finest level a child action stays. ``k`` is set with ``action_mode=ZoomSelect(k=4)``.

**Memory** (``EnvState.memory``): which views of a stride-``T`` grid of every level were seen
(``seen``; the finest level's part says which finest-level views were read) and the counts.
**Observation**: the observation mode's entry, plus ``visited (Gc,)`` float32, the fraction of the
finest tissue views read under each view of the coarsest level's grid (padded to the dataset's
largest, ``Gc = Hc·Wc``), and ``position (3,)`` as ``with_position`` gives it. Bytes per
observation: ``4·(Gc + 3)`` plus the view.

**Reading budget** ``read_budget`` (fraction of finest-level tissue views; ``make(...,
read_budget=…)``): the episode is truncated as soon as the read views reach it (the last child
may overshoot it by one view). **info**: ``fraction_read``, ``fields_of_view`` (distinct views seen
at any level), ``steps``.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from histojax import actions, reading, spaces
from histojax.modes import ActionMode, Move, _declared_score


@struct.dataclass
class ZoomTables:
    """Per-slide tables of ``S`` slides (in ``EnvParams.mode_data``); views on stride-``T`` grids."""

    grid_offset: jnp.ndarray   # (S, n) int32 first index of level z's grid in the flat ``seen`` array
    grid_width: jnp.ndarray    # (S, n) int32 columns of each level's grid
    grid_height: jnp.ndarray   # (S, n) int32 rows of each level's grid
    tissue: jnp.ndarray        # (S, Vf) bool: finest-level view v is a tissue view (flat, padded False)
    coarse_cell: jnp.ndarray   # (S, Vf) int32 coarsest-level grid cell over finest view v (padded Gc: dropped)
    coarse_views: jnp.ndarray  # (S, Gc) float32 tissue views under each coarse cell (≥ 1 to divide by)
    total_views: jnp.ndarray   # (S,) int32 finest-level tissue views of the slide (≥ 1)
    inv_total: jnp.ndarray     # (S,) float32 1 / total_views
    inv_coarse: jnp.ndarray    # (S, Gc) float32 1 / coarse_views
    read_budget: jnp.ndarray   # () float32 fraction of total_views after which the episode is truncated
    seen_zero: jnp.ndarray     # (V,) bool all False: a fresh ``seen`` (V = the largest sum of grid sizes)


@struct.dataclass
class ZoomMemory:
    """What an episode has seen (in ``EnvState.memory``)."""

    seen: jnp.ndarray        # (V,) bool views of every level's grid seen (level z from grid_offset[z])
    views_read: jnp.ndarray  # () int32 finest-level tissue views seen
    fields: jnp.ndarray      # () int32 distinct views seen, any level
    path_x: jnp.ndarray      # (n_levels,) int32 x of the view last zoomed in from at each level (the parents)
    path_y: jnp.ndarray      # (n_levels,) int32


@dataclasses.dataclass(frozen=True)
class ZoomSelect(ActionMode):
    """RLogist-style child selection (see the module doc)."""

    k: int = 2
    name = "zoom_select"

    def validate(self, env) -> None:
        super().validate(env)
        if self.k < 1:
            raise ValueError(f"zoom_select needs k >= 1, got {self.k}")

    def num_actions(self, env) -> int:
        return self.k * self.k + 1 + (2 if env.task == "classification" else 0)

    def space(self, env, params):
        return spaces.Discrete(self.num_actions(env))

    def prepare(self, env, params, bundles, read_budget: float = 1.0) -> ZoomTables:
        if not 0.0 < read_budget <= 1.0:
            raise ValueError(f"read_budget must be in (0, 1], got {read_budget}")
        t = env.tile_size
        rows = {k: [] for k in ("offset", "width", "height", "tissue", "coarse", "total")}
        geoms = []
        for slide, bundle in reading.per_slide(params, bundles):
            _, width, height = reading.level_geometry(slide)
            grids = [reading.grid(int(w), int(h), t, t) for w, h in zip(width, height)]
            geoms.append((slide, bundle, grids))
        big_c = max(g[2][0][0] * g[2][0][1] for g in geoms)
        coarse_views = []
        for slide, bundle, grids in geoms:
            sizes = [h * w for h, w in grids]
            rows["offset"].append(np.cumsum([0] + sizes[:-1]).astype(np.int32))
            rows["width"].append(np.asarray([w for _, w in grids], np.int32))
            rows["height"].append(np.asarray([h for h, _ in grids], np.int32))
            tissue = reading.tissue_views(bundle, slide, t).reshape(-1)
            coarse = reading.cell_of_views(slide, t, 0, t, grids[0]).reshape(-1)
            gh0, gw0 = grids[0]
            counts = np.bincount(coarse[tissue], minlength=gh0 * gw0).astype(np.float32)
            coarse_views.append(np.pad(np.maximum(counts, 1.0), (0, big_c - counts.shape[0]), constant_values=1.0))
            rows["tissue"].append(tissue)
            rows["coarse"].append(coarse.astype(np.int32))
            rows["total"].append(max(1, int(tissue.sum())))
        return ZoomTables(
            grid_offset=jnp.asarray(np.stack(rows["offset"])), grid_width=jnp.asarray(np.stack(rows["width"])),
            grid_height=jnp.asarray(np.stack(rows["height"])),
            tissue=jnp.asarray(reading.pad_stack(rows["tissue"], False)),
            coarse_cell=jnp.asarray(reading.pad_stack(rows["coarse"], big_c)),
            coarse_views=jnp.asarray(np.stack(coarse_views)), total_views=jnp.asarray(rows["total"], jnp.int32),
            inv_total=jnp.asarray(1.0 / np.asarray(rows["total"], np.float64), jnp.float32),
            inv_coarse=jnp.asarray(1.0 / np.stack(coarse_views).astype(np.float64), jnp.float32),
            read_budget=jnp.float32(read_budget),
            seen_zero=jnp.zeros((max(int(o[-1]) + int(w[-1]) * int(h[-1]) for o, w, h in
                                     zip(rows["offset"], rows["width"], rows["height"])),), bool))

    def init_memory(self, env, state, params) -> ZoomMemory:
        zero = jnp.zeros((), jnp.int32)
        path = jnp.zeros((env.n_levels,), jnp.int32)
        memory = ZoomMemory(seen=params.mode_data.seen_zero, views_read=zero, fields=zero, path_x=path, path_y=path)
        return _see(params.mode_data, memory, state.slide_index, state.z, state.x, state.y, env)

    def apply(self, env, state, action, params) -> Move:
        slide = params.slide.select(state.slide_index)
        t, k = env.tile_size, self.k
        a = jnp.asarray(action, jnp.int32)
        finest = env.n_levels - 1
        child = (a >= 0) & (a < k * k) & (state.z < finest)
        z1 = jnp.minimum(state.z + 1, finest)
        ratio = slide.downsample[state.z] / slide.downsample[z1]
        side = t * ratio                                  # footprint side, px of level z + 1
        corner_x = (state.x + t / 2.0) * ratio - side / 2.0
        corner_y = (state.y + t / 2.0) * ratio - side / 2.0
        row, col = jnp.divmod(jnp.clip(a, 0, k * k - 1), k)
        cx = jnp.round(corner_x + (col + 0.5) * side / k - t / 2.0).astype(jnp.int32)
        cy = jnp.round(corner_y + (row + 0.5) * side / k - t / 2.0).astype(jnp.int32)
        cx, cy = actions.clamp_position(slide, z1, cx, cy, t)
        mem = state.memory
        out = (a == k * k) & (state.z > 0)  # back to the view this one was zoomed into from
        parent = jnp.maximum(state.z - 1, 0)
        z = jnp.where(child, z1, jnp.where(out, parent, state.z)).astype(jnp.int32)
        x = jnp.where(child, cx, jnp.where(out, mem.path_x[parent], state.x)).astype(jnp.int32)
        y = jnp.where(child, cy, jnp.where(out, mem.path_y[parent], state.y)).astype(jnp.int32)
        mem = mem.replace(path_x=jnp.where(child, mem.path_x.at[state.z].set(state.x), mem.path_x),
                          path_y=jnp.where(child, mem.path_y.at[state.z].set(state.y), mem.path_y))
        d = k * k + 1
        diagnosis = jnp.where(a == d + 1, 1, jnp.where(a == d, 0, -1)).astype(jnp.int32)
        if env.task != "classification":
            diagnosis = jnp.full((), -1, jnp.int32)
        memory = _see(params.mode_data, mem, state.slide_index, z, x, y, env)
        return Move(z, x, y, diagnosis, _declared_score(diagnosis), memory)

    def budget_spent(self, env, state, params) -> jax.Array:
        tables = params.mode_data
        fraction = state.memory.views_read.astype(jnp.float32) * tables.inv_total[state.slide_index]
        return (tables.read_budget < 1.0) & (fraction >= tables.read_budget)

    def memory_obs(self, env, state, params) -> dict:
        tables, i = params.mode_data, state.slide_index
        f = env.n_levels - 1
        start = tables.grid_offset[i, f]
        n_f = tables.tissue.shape[-1]
        seen_f = jax.lax.dynamic_slice(jnp.pad(state.memory.seen, (0, n_f)), (start,), (n_f,))
        read = (seen_f & tables.tissue[i]).astype(jnp.float32)
        big_c = tables.coarse_views.shape[-1]
        per_cell = jax.ops.segment_sum(read, tables.coarse_cell[i], num_segments=big_c + 1)[:big_c]
        return {"visited": per_cell * tables.inv_coarse[i], "position": _position(env, state, params)}

    def memory_space(self, env, params) -> dict:
        big_c = int(params.mode_data.coarse_views.shape[-1])
        return {"visited": spaces.Box(0.0, 1.0, (big_c,), jnp.float32),
                "position": spaces.Box(0.0, 1.0, (3,), jnp.float32)}

    def reading_info(self, env, state, params) -> dict:
        fraction = state.memory.views_read.astype(jnp.float32) * params.mode_data.inv_total[state.slide_index]
        return {"fraction_read": fraction, "fields_of_view": state.memory.fields}


def _grid_index(tables: ZoomTables, i, z, x, y, tile_size: int):
    """Flat index in ``seen`` of the stride-``T`` grid view nearest ``(z, x, y)``, and its
    position ``(gy, gx)`` in level ``z``'s grid."""
    gw, gh = tables.grid_width[i, z], tables.grid_height[i, z]
    gx = jnp.clip((x + tile_size // 2) // tile_size, 0, gw - 1)
    gy = jnp.clip((y + tile_size // 2) // tile_size, 0, gh - 1)
    return tables.grid_offset[i, z] + gy * gw + gx, gy * gw + gx


def _see(tables: ZoomTables, memory: ZoomMemory, i, z, x, y, env) -> ZoomMemory:
    """``memory`` after looking at ``(z, x, y)``: marks the view, counts it once."""
    index, local = _grid_index(tables, i, z, x, y, env.tile_size)
    new = ~memory.seen[index]
    finest = z == env.n_levels - 1
    tissue = tables.tissue[i, jnp.clip(local, 0, tables.tissue.shape[-1] - 1)]
    return memory.replace(seen=memory.seen.at[index].set(True),
                          views_read=memory.views_read + (new & finest & tissue).astype(jnp.int32),
                          fields=memory.fields + new.astype(jnp.int32))


def _position(env, state, params):
    """``(x_centre / W_z, y_centre / H_z, z / (n_levels - 1))`` float32 (as ``with_position``)."""
    slide = params.slide.select(state.slide_index)
    return env._position(state, slide)
