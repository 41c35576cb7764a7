"""SASHA's reward as an option: a gymnax-style wrapper that rewards reading by a fixed slide head.

HistoGym's reward (and histojax's default) is unchanged unless an env is wrapped::

    from histojax.reading.head_reward import HeadReward
    from histojax.reading import heads

    env, params = histojax.make("HistoJAX-C16-Diagnosis-v2", action_mode="glimpse", read_budget=0.1)
    head = heads.load("baselines/published/c16-v2-head")
    env = HeadReward(env, head, gain="log", final=1.0, read_cost=0.0)   # wraps, like LogWrapper
    obs, state = env.reset(key, params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

After every step the wrapper scores **what has been read so far** with the head
(:func:`histojax.reading.heads.score_logits`: a slide tumour logit from the finest-level views read) and pays

* ``gain``: the head's gain in confidence in the slide's true class, after the step minus before —
  ``"log"``: ``log p(true class)`` (a potential difference: summed over an episode it is the final
  log-probability minus the prior's), ``"prob"``: ``p(true class)``; or ``"fidelity"`` (SASHA's own
  reward, label-free): how much closer the head's slide logit of what has been read came to its logit
  of the whole slide read, ``|s_before − s_all| − |s_after − s_all|`` (logit units; summed over an
  episode, the gap closed). A reader rewarded so learns to read what the read-everything head would
  base its score on, on tumour and normal slides alike, and gains nothing by stopping early;
  ``None`` / ``False``: no gain term;
* ``final``: at the episode's end (terminated or truncated), ``final`` when the head's diagnosis
  (``p(tumour) ≥ 0.5``) is the slide's label, 0 otherwise (``0`` / ``False``: no final term);
* ``read_cost``: subtracted once for every step that reads new finest-level tissue views (a *read*: a
  ``glimpse`` cell revealed, a new finest view visited by a navigator);
* ``env_reward=True`` adds the wrapped env's own reward (default: the head's reward replaces it).

**What counts as read**: for ``glimpse`` the finest tissue views under the cells revealed (the mode's
memory ``revealed``, mapped to the finest grid as :meth:`histojax.reading.modes.glimpse.Glimpse.host_tables` does);
for every other mode (navigation, ``zoom_select``) the wrapper keeps its own bit set of the
finest-level views the episode's view stood on (the grid view nearest the view's top-left corner, as
:func:`histojax.core.seen_views.see` counts them), so the wrapped env is unchanged.

**The navigator's diagnosis through the head**: ``info["head_score"]`` is the head's slide logit of
what the episode has read after the step (at the step where ``terminated | truncated``, the episode's
diagnosis by the head: the navigator chooses where to look, the head declares);
``info["head_correct"]`` whether it is right, ``info["head_views"]`` the finest tissue views read.
``info["success"]`` is the head's diagnosis right at the episode's end (``terminated | truncated`` and
``head_correct``): what a trainer's progress lines and ``histojax evaluate`` through a head call success; the
wrapped env's own success (a declared diagnosis right, a target reached) is ``info["env_success"]``.

**Cost**: with a max-pooling :class:`~histojax.reading.heads.logit.LogitHead` (``top=1``, no median, e.g. the published
``c16-v2-head``) a step re-scores only the window of the 3 × 3 cells (navigators: blocks of ``BLOCK × BLOCK``
finest views) around what it read, giving the same floats as scoring the whole finest grid, at a cost that
does not grow with the slide (:func:`incremental`; ``incremental_score=False`` scores the whole grid).
With a head that pools the read views by attention (:func:`pools_views`: the
:class:`~histojax.reading.heads.learned.LearnedHead`, any encoder's features) the tables hold each finest view's
cached terms (attention, instance logit: :meth:`~histojax.reading.heads.learned.LearnedHead.view_terms`) and the
state three running sums (:class:`~histojax.reading.heads.learned.PoolState`): a step adds the terms of the views
it newly read (a glimpse cell's views, cut from a window of the largest cell's size; a navigator's one new view),
O(views newly read), the same logit as rescoring the whole read set to float rounding.

The wrapper does the auto-reset itself (the same keys as :meth:`histojax.core.env.HistoEnv.step`, so a
trajectory's env states are the unwrapped env's), and its tables (each slide's finest view logits,
tissue views and cells, host-built once) are those of the slides of the params it was made with
(``params``, default the env's own): step it with those params. Pure and jittable: no host
callbacks, no data-dependent Python control flow; ``jax.vmap`` over envs like the env itself.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from histojax.adapters.jax import Wrapper
from histojax.core import seen_views
from histojax.reading import tables as reading_tables
from histojax.reading.heads import score_logits
from histojax.reading.heads.files import check_finite_logits
from histojax.reading.heads.learned import PoolState
from histojax.reading.heads.logit import LogitHead, neighbourhood_mean

GAINS = ("log", "prob", "fidelity")


@struct.dataclass
class HeadTables:
    """Per slide ``S`` of the wrapped env, the finest-level grid padded to ``H × W``."""

    logits: jnp.ndarray  # (S, H, W) float32 the head's view logit (feature entry head.dim) of each finest view
    tissue: jnp.ndarray  # (S, H, W) bool finest tissue views (as the reading modes count them)
    cell: jnp.ndarray  # (S, H, W) int32 glimpse cell (padded index) holding each view; 0 for other modes
    grid: jnp.ndarray  # (S, 2) int32 (gh, gw) each slide's own finest grid
    label: jnp.ndarray  # (S,) int32 slide label (1 tumour)
    full_logit: jnp.ndarray  # (S,) float32 the head's slide logit with every tissue view read
    # glimpse with a max-pooling LogitHead only (else None): the same grids padded by ``k`` views above / left
    # and a window's size below / right, and each cell row's / column's first finest row / column, so that
    # a step re-scores only the window around the cell it revealed (see :meth:`HeadReward._score_incremental`)
    win_logits: jnp.ndarray | None = None  # (S, H + pad_h, W + pad_w) float32
    win_tissue: jnp.ndarray | None = None  # (S, H + pad_h, W + pad_w) bool
    win_cell: jnp.ndarray | None = None  # (S, H + pad_h, W + pad_w) int32
    row_start: jnp.ndarray | None = None  # (S, Gh + 1) int32 first finest row of each cell row (then the end)
    col_start: jnp.ndarray | None = None  # (S, Gw + 1) int32 first finest column of each cell column
    window: tuple = struct.field(pytree_node=False, default=(0, 0))  # (rows, cols) of the re-scored window
    # a head that pools by attention (pools_views) only: each finest view's cached (attention, instance logit)
    terms: jnp.ndarray | None = None  # (S, H, W, 2) float32
    win_terms: jnp.ndarray | None = None  # (S, H + rows, W + cols, 2) glimpse: padded by one cell's window


@struct.dataclass
class HeadRewardState:
    """The wrapped env's state plus what the head has scored."""

    env_state: Any
    visited: jnp.ndarray  # (H·W,) bool finest views visited (non-glimpse modes; with the incremental score the
    # grid of the windows, (k + H + window) × (k + W + window)); (0,) for glimpse
    logit: jnp.ndarray  # () float32 the head's slide logit of what has been read
    views: jnp.ndarray  # () int32 finest tissue views read
    cell_best: jnp.ndarray = None  # (C,) float32 incremental score only: each cell's (navigators: block's)
    # largest neighbourhood mean over its read views (-inf: none read); (0,) otherwise
    pool: PoolState | None = None  # attention-pooling heads (pools_views): the running sums (m, S, Σ e·u (1,))
    # of the views read; a PoolState of empty arrays otherwise


BLOCK = 8  # navigation modes: the incremental score keeps the best of each block of BLOCK × BLOCK finest views


def block_side(head) -> int:
    """Side in finest views of the navigators' blocks of the incremental score (at least the head's ``k``)."""
    return max(BLOCK, int(getattr(head, "k", 1)))


def incremental(head) -> bool:
    """Whether a step can re-score only a window around what it read (exactly the full score): a
    :class:`~histojax.reading.heads.logit.LogitHead` that pools by the maximum (``top=1``, no median), whose neighbourhood
    means change only near newly read views. A ``glimpse`` step reveals at most one cell, a navigator's step
    stands on at most one new finest view; either way the window is the 3 × 3 cells (blocks of
    ``BLOCK × BLOCK`` finest views for navigators) around it."""
    return bool(isinstance(head, LogitHead) and head.top == 1 and not head.minus_median)


def pools_views(head) -> bool:
    """Whether ``head`` pools the read views by attention over cached per-view terms (it has ``view_terms``,
    ``add_terms``, ``logit_terms``: the :class:`~histojax.reading.heads.learned.LearnedHead`), so that a step
    adds the terms of the views it newly read to running sums instead of rescoring the slide."""
    return all(hasattr(head, a) for a in ("view_terms", "add_terms", "logit_terms", "init_terms_state"))


def build_tables(env, head: LogitHead, params=None, windows: bool | None = None) -> HeadTables:
    """Host-built :class:`HeadTables` of ``env``'s slides (``params``: default ``env.default_params``);
    ``windows`` (default :func:`incremental`): also the padded grids of the incremental score."""
    params = env.default_params if params is None else params
    bundles = env.bundles
    if not bundles:
        raise ValueError("HeadReward needs an env made from bundles (histojax.make on a slide or dataset folder)")
    t = env.tile_size
    glimpse = getattr(env.action, "name", "") == "glimpse"
    pooled = pools_views(head)
    rows, all_terms = [], []
    for slide, bundle in seen_views.per_slide(params, bundles):
        if slide.features is None:
            raise ValueError(
                f"{bundle.path}: the slide head reads feature grids; run `python -m data_tools features {bundle.path}`"
            )
        feats = reading_tables.finest_view_features(slide, t)
        if pooled:  # every entry read: per-view scores for the maps, cached terms for the reward
            logits = np.asarray(head.view_logits(feats), np.float32)
            terms = np.asarray(head.view_terms(feats), np.float32)
        else:
            logits, terms = feats[..., head.dim], None
        tissue = seen_views.tissue_views(bundle, slide, t)
        cell = np.zeros(tissue.shape, np.int64)
        starts = None
        if glimpse:
            g, s = env.action.level, int(np.asarray(slide.feature_stride))
            gw, gh = int(np.asarray(slide.feature_grid_width)[g]), int(np.asarray(slide.feature_grid_height)[g])
            own = reading_tables.cell_of_views(slide, t, g, s, (gh, gw))
            cy, cx = np.divmod(own, gw)
            cell = cy * int(np.asarray(params.mode_data.grid)[1]) + cx
            big_h, big_w = (int(v) for v in np.asarray(params.mode_data.grid))
            # cell_of_views is separable and monotone: cell row of finest row r is cy[r, 0], column cx[0, c]
            starts = (np.searchsorted(cy[:, 0], np.arange(big_h + 1)), np.searchsorted(cx[0, :], np.arange(big_w + 1)))
        rows.append((logits, tissue, cell, int(np.asarray(slide.slide_label)), starts))
        all_terms.append(terms)
    h = max(r[1].shape[0] for r in rows)
    w = max(r[1].shape[1] for r in rows)

    def pad(a, fill):
        out = np.full((h, w), fill, a.dtype)
        out[: a.shape[0], : a.shape[1]] = a
        return out

    logits = jnp.asarray(np.stack([pad(r[0].astype(np.float32), 0.0) for r in rows]))
    tissue = jnp.asarray(np.stack([pad(r[1], False) for r in rows]))
    cells = np.stack([pad(r[2], 0) for r in rows])
    extra = {}
    if pooled:
        terms = np.zeros((len(rows), h, w, 2), np.float32)
        for j, tr in enumerate(all_terms):
            terms[j, : tr.shape[0], : tr.shape[1]] = tr
        full = jax.jit(jax.vmap(head.score_terms))(jnp.asarray(terms), tissue)
        check_finite_logits(head, full, "full-read slide logits")  # one line naming params.npz, before any step
        extra["terms"] = jnp.asarray(terms)
        if glimpse:  # a revealed cell's views lie in its rows x columns: cut a window of the largest cell's size
            row_start = np.stack([r[4][0] for r in rows]).astype(np.int32)
            col_start = np.stack([r[4][1] for r in rows]).astype(np.int32)
            win = (max(1, int(np.diff(row_start, axis=1).max())), max(1, int(np.diff(col_start, axis=1).max())))

            def grow(a, fill):
                return np.pad(a, ((0, 0), (0, win[0]), (0, win[1])) + ((0, 0),) * (a.ndim - 3), constant_values=fill)

            extra.update(
                win_terms=jnp.asarray(grow(terms, 0.0)),
                win_tissue=jnp.asarray(grow(np.asarray(tissue), False)),
                win_cell=jnp.asarray(grow(cells, -1), jnp.int32),
                row_start=jnp.asarray(row_start),
                col_start=jnp.asarray(col_start),
                window=win,
            )
    else:
        full = jax.jit(jax.vmap(lambda lg, ts: score_logits(head, lg, ts)))(logits, tissue)
    if not pooled and (incremental(head) if windows is None else windows):
        k = int(head.k)
        if glimpse:
            row_start = np.stack([r[4][0] for r in rows]).astype(np.int32)
            col_start = np.stack([r[4][1] for r in rows]).astype(np.int32)
            win_cells = cells
        else:  # navigators: blocks of BLOCK × BLOCK finest views play the cells
            b = block_side(head)
            nbh, nbw = -(-h // b), -(-w // b)
            row_start = np.broadcast_to(np.minimum(np.arange(nbh + 1) * b, h), (len(rows), nbh + 1)).astype(np.int32)
            col_start = np.broadcast_to(np.minimum(np.arange(nbw + 1) * b, w), (len(rows), nbw + 1)).astype(np.int32)
            block = (np.arange(h)[:, None] // b) * nbw + np.arange(w)[None, :] // b
            win_cells = np.broadcast_to(block, (len(rows), h, w))
        # the re-scored window: the 3 × 3 cells around a revealed one, plus k views on every side
        win = (3 * int(np.diff(row_start, axis=1).max()) + 2 * k, 3 * int(np.diff(col_start, axis=1).max()) + 2 * k)
        grow = lambda a, fill: np.pad(a, ((0, 0), (k, win[0]), (k, win[1])), constant_values=fill)  # noqa: E731
        extra = dict(
            win_logits=jnp.asarray(grow(np.asarray(logits), 0.0)),
            win_tissue=jnp.asarray(grow(np.asarray(tissue), False)),
            win_cell=jnp.asarray(grow(win_cells, 0), jnp.int32),
            row_start=jnp.asarray(row_start),
            col_start=jnp.asarray(col_start),
            window=win,
        )
    return HeadTables(
        logits=logits,
        tissue=tissue,
        cell=jnp.asarray(cells, jnp.int32),
        grid=jnp.asarray([r[1].shape for r in rows], jnp.int32),
        label=jnp.asarray([r[3] for r in rows], jnp.int32),
        full_logit=full.astype(jnp.float32),
        **extra,
    )


class HeadReward(Wrapper):
    """SASHA's reward by a slide head (see the module doc). ``gain``: ``"log"`` (default), ``"prob"`` or
    ``None``; ``final``: reward for a right diagnosis by the head at the episode's end (``True`` = 1.0);
    ``read_cost``: per step that reads new tissue views; ``env_reward``: add the env's own reward;
    ``params``: the env params whose slides the tables hold (default the env's); ``incremental_score``:
    re-score only the window around each revealed cell (default where :func:`incremental` allows it: the
    same logits as scoring the whole grid, at a cost that does not grow with the slide; ``False``: score
    the whole finest grid every step)."""

    def __init__(
        self,
        env,
        head: LogitHead,
        gain: str | None = "log",
        final: float = 1.0,
        read_cost: float = 0.0,
        env_reward: bool = False,
        params=None,
        incremental_score: bool | None = None,
    ):
        super().__init__(env)
        if gain is True:
            gain = "log"
        if gain not in GAINS and gain not in (None, False):
            raise ValueError(f"gain must be one of {GAINS} or None, got {gain!r}")
        if not np.isfinite(float(final)) or not np.isfinite(float(read_cost)) or float(read_cost) < 0:
            raise ValueError(
                f"final must be finite and read_cost finite and ≥ 0, got final={final}, read_cost={read_cost}"
            )
        self.head = head
        self.gain = gain or None
        self.final = float(final)
        self.read_cost = float(read_cost)
        self.env_reward = bool(env_reward)
        self.glimpse = getattr(env.action, "name", "") == "glimpse"
        self.pooled = pools_views(head)  # attention pooling: running sums (O(views newly read)) unless told not to
        self.pool_incremental = self.pooled and incremental_score is not False
        self.incremental = (not self.pooled) and (
            incremental(head) if incremental_score is None else bool(incremental_score)
        )
        if self.incremental and not incremental(head):
            raise ValueError(
                "incremental_score needs a LogitHead with top=1 and no median, or a head that pools "
                "the read views by attention"
            )
        self.tables = build_tables(env, head, params, windows=self.incremental)
        tb = self.tables
        # a navigator's visited views: the finest grid, or with the incremental score the windows' padded grid
        self._offset = int(head.k) if self.incremental else 0
        self._block = block_side(head)  # build_tables' navigator blocks
        self._visited_grid = (
            tuple(tb.win_tissue.shape[1:]) if self.incremental and not self.glimpse else tuple(tb.tissue.shape[1:])
        )

    # ------------------------------------------------------------------ head on a state
    def read_mask(self, env_state, visited) -> jax.Array:
        """``(H, W)`` bool: the finest tissue views read in ``env_state`` (padded grid of the tables)."""
        tb, i = self.tables, env_state.slide_index
        if self.glimpse:
            return env_state.memory.revealed[tb.cell[i]] & tb.tissue[i]
        h, w = tb.tissue.shape[1:]
        o = self._offset
        return visited.reshape(self._visited_grid)[o : o + h, o : o + w] & tb.tissue[i]

    def _finest_view(self, env_state):
        """``(gy, gx, on finest level)``: the finest view under ``env_state``'s view (non-glimpse modes)."""
        tb, i, t = self.tables, env_state.slide_index, self._env.tile_size
        gx = jnp.clip((env_state.x + t // 2) // t, 0, tb.grid[i, 1] - 1)
        gy = jnp.clip((env_state.y + t // 2) // t, 0, tb.grid[i, 0] - 1)
        return gy, gx, env_state.z == self._env.n_levels - 1

    def _visited_index(self, gy, gx):
        """Flat index in ``visited`` of finest view ``(gy, gx)`` (its grid may be padded by ``_offset``)."""
        return (gy + self._offset) * self._visited_grid[1] + gx + self._offset

    def _visit(self, env_state, visited) -> jax.Array:
        """``visited`` with the finest view under ``env_state``'s view marked (non-glimpse modes)."""
        if self.glimpse:
            return visited
        gy, gx, finest = self._finest_view(env_state)
        at = self._visited_index(gy, gx)
        return visited.at[at].set(visited[at] | finest)

    def _score(self, env_state, visited):
        mask = self.read_mask(env_state, visited)
        if self.pooled:  # the whole read set from the cached terms
            return self.head.score_terms(self.tables.terms[env_state.slide_index], mask), mask.sum(dtype=jnp.int32)
        return score_logits(self.head, self.tables.logits[env_state.slide_index], mask), mask.sum(dtype=jnp.int32)

    def _no_pool(self) -> PoolState:
        """The pooling state of a head that keeps none (empty arrays: one pytree per wrapper)."""
        return PoolState(jnp.zeros((0,), jnp.float32), jnp.zeros((0,), jnp.float32), jnp.zeros((0,), jnp.float32))

    def _score_pooled(self, before: HeadRewardState, env_state, visited):
        """``(logit, views, pool)`` after a step from ``before`` for an attention-pooling head: the cached terms
        of the views the step newly read added to ``before.pool`` (a glimpse step: the tissue views of the one
        cell it revealed, cut from a window of the largest cell's size at the cell's first row and column; a
        navigator's step: the finest tissue view it stands on, if new). O(views newly read)."""
        tb, head, i = self.tables, self.head, env_state.slide_index
        if self.glimpse:
            revealed = env_state.memory.revealed
            changed = revealed & ~before.env_state.memory.revealed
            c = jnp.argmax(changed)
            big_w = tb.col_start.shape[1] - 1
            oy, ox = tb.row_start[i, c // big_w], tb.col_start[i, c % big_w]
            cell = jax.lax.dynamic_slice(tb.win_cell[i], (oy, ox), tb.window)
            tissue = jax.lax.dynamic_slice(tb.win_tissue[i], (oy, ox), tb.window)
            terms = jax.lax.dynamic_slice(tb.win_terms[i], (oy, ox, 0), tb.window + (2,))
            new = (cell == c) & tissue & changed.any()
            pool = head.add_terms(before.pool, terms.reshape(-1, 2), new.reshape(-1))
            views = before.views + new.sum(dtype=jnp.int32)
        else:
            vy, vx, finest = self._finest_view(env_state)
            new = finest & ~before.visited[self._visited_index(vy, vx)] & tb.tissue[i, vy, vx]
            pool = head.add_terms(before.pool, tb.terms[i, vy, vx][None], new[None])
            views = before.views + new.astype(jnp.int32)
        return head.logit_terms(pool), views, pool

    def _score_incremental(self, before: HeadRewardState, env_state, visited):
        """``(logit, views, cell_best)`` after a step from ``before``, re-scoring only the window of the
        3 × 3 cells around the cell the step revealed (a glimpse step reveals at most one): a read view's
        ``k × k`` neighbourhood mean changes only when a view of its window is newly read, and those views
        lie in that window (navigators: the 3 × 3 blocks around the finest view stood on; ``visited`` after
        the step). The same floats as :meth:`_score` (the same sums of the same views)."""
        tb, head, i = self.tables, self.head, env_state.slide_index
        big_w = tb.col_start.shape[1] - 1  # the padded cell grid (static)
        if self.glimpse:
            revealed = env_state.memory.revealed
            changed = revealed & ~before.env_state.memory.revealed
            new = changed.any()
            c = jnp.argmax(changed)
        else:  # a navigator: the finest view it stands on, if new and on tissue; its block plays the cell
            vy, vx, finest = self._finest_view(env_state)
            new = finest & ~before.visited[self._visited_index(vy, vx)] & tb.tissue[i, vy, vx]
            c = (vy // self._block) * big_w + vx // self._block
        gy, gx = c // big_w, c % big_w
        oy = tb.row_start[i, jnp.maximum(gy - 1, 0)]  # padded grid: k views above, so the window starts k higher
        ox = tb.col_start[i, jnp.maximum(gx - 1, 0)]
        cut = lambda a: jax.lax.dynamic_slice(a[i], (oy, ox), tb.window)  # noqa: E731
        cell, tissue = cut(tb.win_cell), cut(tb.win_tissue)
        if self.glimpse:
            read = revealed[cell] & tissue
        else:
            read = jax.lax.dynamic_slice(visited.reshape(self._visited_grid), (oy, ox), tb.window) & tissue
        nb = neighbourhood_mean(cut(tb.win_logits), read, head.k)
        big_h = tb.row_start.shape[1] - 1
        near = (
            jnp.clip(gy + jnp.array([-1, 0, 1]), 0, big_h - 1)[:, None] * big_w
            + jnp.clip(gx + jnp.array([-1, 0, 1]), 0, big_w - 1)[None, :]
        ).reshape(-1)  # (9,) cells
        best = jnp.where((cell[None] == near[:, None, None]) & read[None], nb[None], -jnp.inf).max((1, 2))
        cell_best = jnp.where(new, before.cell_best.at[near].set(best), before.cell_best)
        if self.glimpse:
            views = before.views + jnp.where(new, ((cell == c) & tissue).sum(dtype=jnp.int32), 0)
        else:
            views = before.views + new.astype(jnp.int32)
        s = cell_best.max()
        logit = jnp.where(views > 0, head.cal_a * s + head.cal_b, head.prior_logit).astype(jnp.float32)
        return logit, views, cell_best

    def _wrap(self, env_state) -> HeadRewardState:
        n = 0 if self.glimpse else int(np.prod(self._visited_grid))
        empty = jnp.zeros((n,), bool)
        visited = self._visit(env_state, empty)
        if self.pool_incremental:  # a fresh episode: nothing read (glimpse), or the one view stood on (navigators)
            nothing = HeadRewardState(
                env_state=env_state,
                visited=empty,
                views=jnp.zeros((), jnp.int32),
                logit=jnp.asarray(self.head.prior_logit, jnp.float32),
                cell_best=jnp.zeros((0,), jnp.float32),
                pool=self.head.init_terms_state(),
            )
            if self.glimpse:
                return nothing
            logit, views, pool = self._score_pooled(nothing, env_state, visited)
            return nothing.replace(visited=visited, logit=logit, views=views, pool=pool)
        if (
            self.incremental
        ):  # a fresh episode: nothing read (a glimpse reset reveals nothing), or the one view stood on
            cells = (self.tables.row_start.shape[1] - 1) * (self.tables.col_start.shape[1] - 1)
            nothing = HeadRewardState(
                env_state=env_state,
                visited=empty,
                views=jnp.zeros((), jnp.int32),
                logit=jnp.asarray(self.head.prior_logit, jnp.float32),
                cell_best=jnp.full((cells,), -jnp.inf, jnp.float32),
                pool=self._no_pool(),
            )
            if self.glimpse:
                return nothing
            logit, views, cell_best = self._score_incremental(nothing, env_state, visited)
            return nothing.replace(visited=visited, logit=logit, views=views, cell_best=cell_best)
        logit, views = self._score(env_state, visited)
        return HeadRewardState(
            env_state=env_state,
            visited=visited,
            logit=logit,
            views=views,
            cell_best=jnp.zeros((0,), jnp.float32),
            pool=self.head.init_terms_state() if self.pooled else self._no_pool(),
        )

    def log_prob_true(self, logit, label) -> jax.Array:
        """``log p(label)`` of a slide logit (label 1: tumour)."""
        return jnp.where(label == 1, jax.nn.log_sigmoid(logit), jax.nn.log_sigmoid(-logit))

    # ------------------------------------------------------------------ gymnax API
    def reset(self, key, params=None):
        """``(obs, HeadRewardState)``."""
        params = self._env.default_params if params is None else params
        obs, env_state = self._env.reset_env(key, params)
        return obs, self._wrap(env_state)

    def step(self, key, state: HeadRewardState, action, params=None):
        """``(obs, state, reward, terminated, truncated, info)``: the env's step (auto-reset as the env's
        own), the reward of the module doc, ``info`` plus ``head_score``, ``head_correct``, ``head_views``,
        ``head_reward``."""
        params = self._env.default_params if params is None else params
        key_reset, _ = jax.random.split(key)
        obs_st, env_st, env_r, terminated, truncated, info = self._env.step_env(key, state.env_state, action, params)
        visited = self._visit(env_st, state.visited)
        pool = state.pool
        if self.pool_incremental:
            (logit, views, pool), cell_best = self._score_pooled(state, env_st, visited), state.cell_best
        elif self.incremental:
            logit, views, cell_best = self._score_incremental(state, env_st, visited)
        else:
            (logit, views), cell_best = self._score(env_st, visited), state.cell_best
        label = self.tables.label[env_st.slide_index]
        done = terminated | truncated
        correct = (logit >= 0.0) == (label == 1)
        reward = jnp.zeros((), jnp.float32)
        if self.gain == "log":
            reward = reward + self.log_prob_true(logit, label) - self.log_prob_true(state.logit, label)
        elif self.gain == "prob":
            reward = (
                reward + jnp.exp(self.log_prob_true(logit, label)) - jnp.exp(self.log_prob_true(state.logit, label))
            )
        elif self.gain == "fidelity":
            full = self.tables.full_logit[env_st.slide_index]
            reward = reward + jnp.abs(state.logit - full) - jnp.abs(logit - full)
        if self.final:
            reward = reward + jnp.where(done & correct, self.final, 0.0)
        if self.read_cost:
            reward = reward - jnp.where(views > state.views, self.read_cost, 0.0)
        head_reward = reward.astype(jnp.float32)
        if self.env_reward:
            reward = reward + env_r
        # success: the head's diagnosis right at the episode's end (what histojax evaluate calls success through a
        # head); the env's own success (a declared diagnosis, a target reached) stays in env_success
        info = {
            **info,
            "env_success": info.get("success", jnp.bool_(False)),
            "success": done & correct,
            "head_score": logit,
            "head_correct": correct,
            "head_views": views,
            "head_reward": head_reward,
        }
        new = HeadRewardState(
            env_state=env_st, visited=visited, logit=logit, views=views, cell_best=cell_best, pool=pool
        )
        if not self._env.auto_reset:
            return obs_st, new, reward.astype(jnp.float32), terminated, truncated, {**info, "final_observation": obs_st}
        obs_re, env_re = self._env.reset_env(key_reset, params)
        fresh = self._wrap(env_re)
        out = jax.tree.map(lambda a, b: jnp.where(done, a, b), fresh, new)
        obs = jax.tree.map(lambda a, b: jnp.where(done, a, b), obs_re, obs_st)
        if self._env.final_observation:
            info["final_observation"] = obs_st
        return obs, out, reward.astype(jnp.float32), terminated, truncated, info
