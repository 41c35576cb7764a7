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
updated at each step, so the observation never recounts the slide's views). Both carry an episode
stamp (:class:`ZoomMemory`), so the auto-reset starts an episode without writing the whole memory.
**Observation**: the observation mode's entry, plus ``visited (16, 16)`` float32, the coarse
visited map of :mod:`histojax.core.seen_views` (the fraction of the finest tissue views read in each of
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

from histojax.core import actions, seen_views, spaces
from histojax.core.modes.base import ActionMode, Move, _declared_score


@struct.dataclass
class ZoomMemory:
    """What an episode has seen (in ``EnvState.memory``).

    The bit set and the visited-map counts carry an **episode stamp**: a word of ``words`` (a block of
    ``block_raw``) counts only where its stamp equals ``episode``, else it reads as 0. Starting an episode
    in the auto-reset adds 1 to ``episode`` instead of writing zeros over the whole memory, so a step
    writes one word and one block whatever the slide's size. Read the bits and counts through
    :attr:`seen` and :attr:`block_read` (they apply the stamps; any leading batch axes are fine)."""

    words: jnp.ndarray  # (⌈V/32⌉,) uint32 raw bits: views of every level's grid seen (histojax.core.seen_views.see)
    stamp: jnp.ndarray  # (⌈V/32⌉,) int32 the episode that last wrote each word
    views_read: jnp.ndarray  # () int32 finest-level tissue views seen
    fields: jnp.ndarray  # () int32 distinct views seen, any level
    block_raw: jnp.ndarray  # (256,) int32 raw finest tissue views read per block of the visited map
    block_stamp: jnp.ndarray  # (256,) int32 the episode that last wrote each block
    path_x: jnp.ndarray  # (n_levels,) int32 x of the view last zoomed in from at each level (the parents)
    path_y: jnp.ndarray  # (n_levels,) int32
    episode: jnp.ndarray  # () int32 episodes started by this env's auto-reset since ``reset`` (0 first)

    @property
    def seen(self) -> jax.Array:
        """``(..., ⌈V/32⌉)`` uint32: this episode's bits (stale words of earlier episodes read as 0)."""
        return jnp.where(self.stamp == jnp.asarray(self.episode)[..., None], self.words, jnp.uint32(0))

    @property
    def block_read(self) -> jax.Array:
        """``(..., 256)`` int32: this episode's finest tissue views read per block of the visited map."""
        return jnp.where(self.block_stamp == jnp.asarray(self.episode)[..., None], self.block_raw, 0)


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

    def prepare(self, env, params, bundles, read_budget: float = 1.0) -> seen_views.SeenTables:
        return seen_views.seen_tables(env, params, bundles, read_budget)

    def init_memory(self, env, state, params) -> ZoomMemory:
        zero = jnp.zeros((), jnp.int32)
        path = jnp.zeros((env.n_levels,), jnp.int32)
        words = params.mode_data.seen_zero
        blocks = seen_views.block_zero(params.mode_data)
        memory = ZoomMemory(
            words=words,
            stamp=jnp.zeros(words.shape, jnp.int32),
            views_read=zero,
            fields=zero,
            block_raw=blocks,
            block_stamp=blocks,
            path_x=path,
            path_y=path,
            episode=zero,
        )
        return seen_views.see(params.mode_data, memory, state.slide_index, state.z, state.x, state.y, env)

    def auto_reset_memory(self, env, done, memory, state, params) -> ZoomMemory:
        """A new episode where ``done``: ``episode`` + 1 (every word and block goes stale at once), counts and
        path to 0, then the start view of ``state`` seen. A start view is at the coarsest level and new, so
        (with more than one level) seeing it is one bit in one word and one field, and reads nothing: only
        that word and its stamp are written, and nothing where not ``done``."""
        zero = jnp.zeros((), jnp.int32)
        episode = memory.episode + done.astype(jnp.int32)
        fresh = memory.replace(
            episode=episode,
            views_read=jnp.where(done, zero, memory.views_read),
            fields=jnp.where(done, zero, memory.fields),
            path_x=jnp.where(done, 0, memory.path_x),
            path_y=jnp.where(done, 0, memory.path_y),
        )
        if env.n_levels == 1:  # the start view is a finest view: it may be read (a block of the visited map counts it)
            return jax.tree.map(
                lambda a, b: jnp.where(done, a, b),
                seen_views.see(params.mode_data, fresh, state.slide_index, state.z, state.x, state.y, env),
                memory,
            )
        index, _ = seen_views._grid_index(params.mode_data, state.slide_index, state.z, state.x, state.y, env.tile_size)
        word = jnp.where(done, index // 32, memory.words.shape[-1])  # out of range where not done: dropped
        bit = jnp.left_shift(jnp.uint32(1), (index % 32).astype(jnp.uint32))
        return fresh.replace(
            words=memory.words.at[word].set(bit, mode="drop"),
            stamp=memory.stamp.at[word].set(episode, mode="drop"),
            fields=jnp.where(done, 1, memory.fields),
        )

    def apply(self, env, state, action, params) -> Move:
        slide = params.slide.select(state.slide_index)
        t, k = env.tile_size, self.k
        a = jnp.asarray(action, jnp.int32)
        finest = env.n_levels - 1
        child = (a >= 0) & (a < k * k) & (state.z < finest)
        z1 = jnp.minimum(state.z + 1, finest)
        ratio = slide.downsample[state.z] / slide.downsample[z1]
        side = t * ratio  # footprint side, px of level z + 1
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
        mem = mem.replace(
            path_x=jnp.where(child, mem.path_x.at[state.z].set(state.x), mem.path_x),
            path_y=jnp.where(child, mem.path_y.at[state.z].set(state.y), mem.path_y),
        )
        d = k * k + 1
        diagnosis = jnp.where(a == d + 1, 1, jnp.where(a == d, 0, -1)).astype(jnp.int32)
        if env.task != "classification":
            diagnosis = jnp.full((), -1, jnp.int32)
        memory = seen_views.see(params.mode_data, mem, state.slide_index, z, x, y, env)
        return Move(z, x, y, diagnosis, _declared_score(diagnosis), memory)

    def budget_spent(self, env, state, params) -> jax.Array:
        return seen_views.budget_spent(params.mode_data, state.memory, state.slide_index)

    def memory_obs(self, env, state, params) -> dict:
        return seen_views.visited_obs(env, state, params)

    def memory_space(self, env, params) -> dict:
        return seen_views.visited_space(params)

    def reading_info(self, env, state, params) -> dict:
        return seen_views.reading_info(params.mode_data, state.memory, state.slide_index)
