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
(``seen``, one bit a view in uint32 words; the finest level's part says which finest-level views were
read), the counts, and the finest tissue views read per block of the visited map (``block_read``,
updated at each step, so the observation never recounts the slide's views).
**Observation**: the observation mode's entry, plus ``visited (16, 16)`` float32, the coarse
visited map of :mod:`histojax.reading` (the fraction of the finest tissue views read in each of
16 × 16 blocks of the slide), and ``position (3,)`` as ``with_position`` gives it. Bytes per
observation: ``4·(256 + 3) = 1036`` plus the view.

**Reading budget** ``read_budget`` (fraction of finest-level tissue views; ``make(...,
read_budget=…)``): the episode is truncated as soon as the read views reach it (the last child
may overshoot it by one view). **info**: ``fraction_read``, ``fields_of_view`` (distinct views seen
at any level), ``steps``.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from flax import struct

from histojax import actions, reading, spaces
from histojax.modes import ActionMode, Move, _declared_score


@struct.dataclass
class ZoomMemory:
    """What an episode has seen (in ``EnvState.memory``)."""

    seen: jnp.ndarray        # (⌈V/32⌉,) uint32 bits: views of every level's grid seen (see histojax.reading.see)
    views_read: jnp.ndarray  # () int32 finest-level tissue views seen
    fields: jnp.ndarray      # () int32 distinct views seen, any level
    block_read: jnp.ndarray  # (256,) int32 finest tissue views read per block of the visited map
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

    def prepare(self, env, params, bundles, read_budget: float = 1.0) -> reading.SeenTables:
        return reading.seen_tables(env, params, bundles, read_budget)

    def init_memory(self, env, state, params) -> ZoomMemory:
        zero = jnp.zeros((), jnp.int32)
        path = jnp.zeros((env.n_levels,), jnp.int32)
        memory = ZoomMemory(seen=params.mode_data.seen_zero, views_read=zero, fields=zero,
                            block_read=reading.block_zero(params.mode_data), path_x=path, path_y=path)
        return reading.see(params.mode_data, memory, state.slide_index, state.z, state.x, state.y, env)

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
        memory = reading.see(params.mode_data, mem, state.slide_index, z, x, y, env)
        return Move(z, x, y, diagnosis, _declared_score(diagnosis), memory)

    def budget_spent(self, env, state, params) -> jax.Array:
        return reading.budget_spent(params.mode_data, state.memory, state.slide_index)

    def memory_obs(self, env, state, params) -> dict:
        return reading.visited_obs(env, state, params)

    def memory_space(self, env, params) -> dict:
        return reading.visited_space(params)

    def reading_info(self, env, state, params) -> dict:
        return reading.reading_info(params.mode_data, state.memory, state.slide_index)
