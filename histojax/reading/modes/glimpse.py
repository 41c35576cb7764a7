"""``action_mode="glimpse"`` (SASHA style): pick cells of a fixed low-magnification grid, read what
lies under them at the finest level, diagnose.

**Cells** are the feature-grid views of scenario level ``level`` (default 0, the coarsest; the
grid step is the bundle's feature stride, ``T`` px by default), padded to the dataset's largest
grid ``Gh × Gw`` (``C = Gh·Gw`` cells, index ``gy·Gw + gx``). A cell is *valid* when it lies on the
slide and at least one finest-level tissue view lies under it (:mod:`histojax.core.seen_views`).

**Actions** ``Discrete(C + 2)``: ``i < C`` picks cell ``i``; ``C`` declares no tumour, ``C + 1``
declares tumour (``task="classification"`` only). Picking a valid, unread cell *reveals* it: the
summary of the finest-level tissue views under it — the **mean and the elementwise max** of their
feature vectors, ``(2D,)`` (the mean says what the cell mostly is, the max keeps a small focus of
tumour that the mean would dilute; attention-MIL heads read both well) — and its views count as
read. Picking a cell again, an invalid cell, or a padding cell reveals nothing new (the step still
costs ``step_cost``). The view in the state moves to the picked cell (level ``level``).

**Reading budget** ``read_budget`` (a fraction of the slide's finest-level tissue views, in
``params.mode_data``; ``make(..., read_budget=0.2)`` or :func:`with_budget`): a pick that would
read past it reveals nothing and ends the episode (truncated, no diagnosis); so does reading
exactly the whole budget. Reading never exceeds the budget.

**Observation**: the observation mode's entry of the current view, plus (all float32, ``C`` cells)
``cells (C, D)`` low-resolution features of every cell (0 for padding), ``valid (C,)`` 0/1,
``revealed (C,)`` 0/1, ``summaries (C, 2D)`` the revealed summaries (0 where unread) and
``budget_left ()`` the budget not yet read (``read_budget − fraction_read``). Bytes per observation:
``4 · C · (3D + 2) + 4`` plus the view entry (see :func:`observation_bytes`).

**Step observation** (``step_obs=True``, the ``-v2`` ids): what is fixed for a slide during an episode
comes once from :meth:`Glimpse.episode_tables` (``env.episode_tables(params)``); a step carries the view
entry, ``slide ()`` int32, ``read_bits (⌈C/32⌉,)`` uint32 (:func:`unpack_bits`), ``read_cells (K,)``
int32 (the cells read in order, ``C`` for an empty slot), ``read_summaries (K, 2D)`` in the feature
bank's dtype and ``budget_left ()``. ``K`` (``read_slots``) is by default the most cells the budget
lets an episode read; a new cell without a free slot ends the episode like the budget.

**info** (every step): ``fraction_read`` (read tissue views / all tissue views), ``fields_of_view``
(distinct cells revealed), ``steps``; with ``score`` / ``declared`` of classification.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from histojax.core import seen_views, spaces
from histojax.core.modes.base import ActionMode, Move, _declared_score
from histojax.reading import tables as reading_tables


@struct.dataclass
class GlimpseTables:
    """Per-slide tables of a dataset of ``S`` slides, ``C`` cells (in ``EnvParams.mode_data``)."""

    cells: jnp.ndarray  # (S, C, D) float32 low-resolution features of each cell (0: padding)
    summaries: jnp.ndarray  # (S, C, 2D) float32 mean ‖ max of the finest tissue views' features under it
    cell_views: jnp.ndarray  # (S, C) int32 finest-level tissue views under each cell
    valid: jnp.ndarray  # (S, C) bool: on the slide with ≥ 1 tissue view under it
    cell_x: jnp.ndarray  # (S, C) int32 top-left of the cell's view, px of the glimpse level
    cell_y: jnp.ndarray  # (S, C) int32
    total_views: jnp.ndarray  # (S,) int32 finest-level tissue views of the slide (≥ 1)
    inv_total: jnp.ndarray  # (S,) float32 1 / total_views (a product, not a division, is bitwise stable under vmap)
    read_budget: jnp.ndarray  # () float32 fraction of total_views an episode may read, in (0, 1]
    grid: jnp.ndarray  # (2,) int32 (H, W): the padded cell grid, C = H · W (cell index = row · W + col)
    slots_zero: jnp.ndarray  # (K,) int32 all C: an empty list of the cells read (K = read_slots, see the module doc)
    slide_grid: jnp.ndarray  # (S, 2) int32 (gh, gw): each slide's own cell grid, inside the padded one
    step_obs: bool = struct.field(pytree_node=False, default=False)  # made for a step_obs env: no policy depends on C


@struct.dataclass
class GlimpseMemory:
    """What an episode has read (in ``EnvState.memory``)."""

    revealed: jnp.ndarray  # (C,) bool cells revealed so far
    views_read: jnp.ndarray  # () int32 finest-level tissue views read so far
    fields: jnp.ndarray  # () int32 distinct cells revealed (fields of view)
    over_budget: jnp.ndarray  # () bool a pick was refused by the budget (the episode ends)
    slots: jnp.ndarray = None  # (K,) int32 the cells revealed, in reading order; step_obs envs only
    slot_summaries: jnp.ndarray = None  # (K, 2D) their summaries in the feature bank's dtype; step_obs only
    # only the first ``fields`` slots are this episode's: the auto-reset leaves the others as they were
    # (the observation shows them empty: cell C, summary 0)


def with_budget(params, read_budget: float):
    """``params`` with another reading budget (fraction in ``(0, 1]``; no recompilation)."""
    return params.replace(mode_data=params.mode_data.replace(read_budget=jnp.float32(read_budget)))


def budget_views(tables: GlimpseTables, slide_index) -> jax.Array:
    """The most tissue views an episode on slide ``slide_index`` may read (int32)."""
    total = tables.total_views[slide_index]
    return jnp.floor(tables.read_budget * total.astype(jnp.float32) + 1e-4).astype(jnp.int32)


def slots_needed(cell_views: np.ndarray, valid: np.ndarray, total: np.ndarray, read_budget: float) -> int:
    """Host: the most cells any episode can reveal within ``read_budget`` on these slides (``cell_views``,
    ``valid`` ``(S, C)``, ``total`` ``(S,)``): per slide, its smallest valid cells first, as many as fit the
    budget's views (the bound is reached by reading the smallest cells); at least 1."""
    most = 1
    for views, ok, n in zip(cell_views, valid, total):
        budget = int(np.floor(np.float32(read_budget) * np.float32(n) + np.float32(1e-4)))
        cum = np.cumsum(np.sort(views[ok]))
        most = max(most, int(np.searchsorted(cum, budget, side="right")))
    return most


def smallest_cells(cell_views, valid) -> np.ndarray:
    """Host: per slide ``(S,)`` float64, the finest-level tissue views of its smallest valid cell (``cell_views``,
    ``valid``: ``(S, C)`` or a list of ``(C,)``); ``inf`` for a slide without a valid cell."""
    out = []
    for views, ok in zip(cell_views, valid):
        views, ok = np.asarray(views), np.asarray(ok, bool)
        out.append(float(views[ok].min()) if ok.any() else np.inf)
    return np.asarray(out, np.float64)


def smallest_budgets(cell_views, valid, total) -> np.ndarray:
    """Host: per slide ``(S,)`` float64, the smallest reading budget (a fraction of the slide's finest-level tissue
    views) at which one cell can be read by :func:`budget_views`' rule: its smallest valid cell's views
    (:func:`smallest_cells`) over its ``total`` views ``(S,)``; ``inf`` for a slide without a valid cell. Below it an
    episode on that slide reads nothing."""
    total = np.maximum(np.atleast_1d(np.asarray(total, np.float64)).reshape(-1), 1.0)
    return smallest_cells(cell_views, valid) / total


def _percent_up(fraction: float) -> str:
    """``fraction`` as a percentage rounded up to 0.1 % (a budget that reads, printed so it still reads)."""
    return f"{np.ceil(fraction * 1000.0 - 1e-6) / 10.0:.1f} %"


def _percent(fraction: float) -> str:
    return f"{fraction * 100:.3g} %"


def unreadable_warning(names, cell_views, valid, total, budgets, where: str = "") -> str | None:
    """One line when at some of ``budgets`` (fractions in ``(0, 1]``) nothing can be read on some slides (their
    smallest cell holds more finest-level tissue views than the budget allows: :func:`budget_views`' rule,
    :func:`smallest_cells`): which budgets, how many of the ``S`` slides, the slides' ``names`` (at the smallest such
    budget; five named, then a count) and the nearest budget that reads a cell on every slide
    (:func:`smallest_budgets`). What a reader scores there is the overview alone (nothing read on any slide: AUC
    0.500). ``cell_views``, ``valid``: ``(S, C)``; ``total``: ``(S,)``. ``where``: said first (e.g. the run's
    folder). ``None`` when every budget reads something on every slide."""
    cells = smallest_cells(cell_views, valid)
    total = np.atleast_1d(np.asarray(total)).reshape(-1)
    names = list(names)
    empty = []
    for b in sorted({float(b) for b in budgets}):
        allowed = np.floor(np.float32(b) * total.astype(np.float32) + np.float32(1e-4))  # budget_views, on the host
        idx = np.flatnonzero(allowed < cells)
        if idx.size:
            empty.append((b, idx))
    if not empty:
        return None
    b0, idx0 = empty[0]
    shown = ", ".join(str(names[i]) for i in idx0[:5]) + (f" and {idx0.size - 5} more" if idx0.size > 5 else "")
    need = smallest_budgets(cell_views, valid, total)
    finite = need[np.isfinite(need)]
    nearest = (
        f"the nearest budget that reads a cell on every slide is {_percent_up(float(finite.max()))}"
        if finite.size
        else "no slide has a cell to read"
    )
    if len(empty) == 1:
        said = f"at read budget {_percent(b0)} on {idx0.size} of {cells.size} slides ({shown})"
    else:
        said = (
            f"at read budgets {', '.join(_percent(b) for b, _ in empty)} on "
            f"{', '.join(str(i.size) for _, i in empty)} of {cells.size} slides (at {_percent(b0)}: {shown})"
        )
    return (
        f"{where + ': ' if where else ''}nothing can be read {said}: each of their cells holds more tissue views "
        "than the budget allows, so what is scored there is the overview alone (AUC 0.500 where no slide reads "
        f"anything); {nearest}"
    )


@dataclasses.dataclass(frozen=True)
class Glimpse(ActionMode):
    """SASHA-style cell picking (see the module doc). ``level``: the cell grid's scenario level."""

    level: int = 0
    name = "glimpse"
    needs_features = True
    tasks = ("classification",)

    def validate(self, env) -> None:
        super().validate(env)
        if not 0 <= self.level < env.n_levels:
            raise ValueError(f"glimpse level must be in [0, {env.n_levels}), got {self.level}")

    def num_actions(self, env) -> int:
        return self.num_cells(env.default_params) + 2

    def num_cells(self, params) -> int:
        """``C``, the padded number of cells (static: from the tables' shape)."""
        return int(params.mode_data.valid.shape[-1])

    def space(self, env, params):
        return spaces.Discrete(self.num_cells(params) + 2)

    def prepare(
        self, env, params, bundles, read_budget: float = 1.0, glimpse_grid=None, read_slots: int | None = None
    ) -> GlimpseTables:
        """``glimpse_grid=(H, W)``: pad every slide's cells to that grid (default: the largest grid of these
        slides; only the v1 observation, which holds every cell, needs it to match across datasets).
        ``read_slots``: ``K``, the slots of the cells-read list of an ``episode_tables`` observation
        (default: the most cells an episode can reveal within ``read_budget``, :func:`slots_needed`)."""
        if not 0.0 < read_budget <= 1.0:
            raise ValueError(f"read_budget must be in (0, 1], got {read_budget}")
        if read_slots is not None and int(read_slots) < 1:
            raise ValueError(f"read_slots must be a whole number >= 1, got {read_slots}")
        per = self.host_tables(env, params, bundles, grid=glimpse_grid, instances=False)
        stack = lambda k, dtype=None: np.stack([p[k] for p in per]).astype(dtype)  # noqa: E731
        total = np.asarray([p["total"] for p in per])
        cell_views, valid = stack("cell_views", np.int32), stack("valid", bool)
        c = cell_views.shape[1]
        k = int(read_slots) if read_slots is not None else slots_needed(cell_views, valid, total, read_budget)
        return GlimpseTables(
            cells=jnp.asarray(stack("cells")),
            summaries=jnp.asarray(stack("summaries")),
            cell_views=jnp.asarray(cell_views),
            valid=jnp.asarray(valid),
            cell_x=jnp.asarray(stack("cell_x")),
            cell_y=jnp.asarray(stack("cell_y")),
            total_views=jnp.asarray(total, jnp.int32),
            inv_total=jnp.asarray(1.0 / total.astype(np.float64), jnp.float32),
            read_budget=jnp.float32(read_budget),
            grid=jnp.asarray(per[0]["grid"], jnp.int32),
            slots_zero=jnp.full((min(k, c),), c, jnp.int32),
            slide_grid=jnp.asarray(stack("slide_grid", np.int32)),
            step_obs=bool(env.step_obs),
        )

    def host_tables(self, env, params, bundles, grid=None, instances: bool = True) -> list[dict]:
        """Per slide, host numpy: the padded cell tables of :class:`GlimpseTables` (``cells``,
        ``summaries``, ``cell_views``, ``valid``, ``cell_x``, ``cell_y``, ``total``, ``grid``) and the
        instances behind them: ``instances (V, D)`` features of the slide's finest-level tissue views and
        ``instance_cell (V,)`` the (padded) cell index, i.e. the action, that reveals each. ``grid``:
        ``(H, W)`` to pad to (``ValueError`` naming a slide whose cells do not fit); default the largest.
        ``instances=False``: without ``instances`` / ``instance_cell`` (what ``prepare`` needs)."""
        t, g = env.tile_size, self.level
        per = []
        for slide, bundle in seen_views.per_slide(params, bundles):
            if slide.features is None:
                raise ValueError(
                    f"action_mode='glimpse' needs feature grids: run `python -m data_tools features {bundle.path}`"
                )
            s = int(np.asarray(slide.feature_stride))
            gw, gh = int(np.asarray(slide.feature_grid_width)[g]), int(np.asarray(slide.feature_grid_height)[g])
            per.append((bundle, s, gh, gw))  # not the slide's view: it is made again below, one at a time
        big_h, big_w = max(p[2] for p in per), max(p[3] for p in per)
        if grid is not None:
            gh_max, gw_max = (int(v) for v in grid)
            for bundle, _, gh, gw in per:
                if gh > gh_max or gw > gw_max:
                    raise ValueError(
                        f"{bundle.path}: its {gh} × {gw} glimpse cells at level {self.level} do not fit "
                        f"glimpse_grid={[gh_max, gw_max]} (the grid a policy was trained with); "
                        "train on slides that include one this large, or pass a larger glimpse_grid"
                    )
            big_h, big_w = gh_max, gw_max
        out = []
        for (slide, _), (bundle, s, gh, gw) in zip(seen_views.per_slide(params, bundles), per):
            tissue = seen_views.tissue_views(bundle, slide, t).reshape(-1)
            cell = reading_tables.cell_of_views(slide, t, g, s, (gh, gw)).reshape(-1)
            feats = reading_tables.finest_view_features(slide, t).reshape(tissue.shape[0], -1)
            n = gh * gw
            mean, mx, count = cell_summaries(feats[tissue], cell[tissue], n)
            low = reading_tables.feature_rows(slide, int(np.asarray(slide.feature_offset)[g]) + np.arange(n))
            gy, gx = np.divmod(np.arange(n), gw)
            pad = lambda a, fill=0: _to_padded(a.reshape(gh, gw, *a.shape[1:]), big_h, big_w, fill)  # noqa: E731
            row = {
                "cells": pad(low),
                "summaries": pad(np.concatenate([mean, mx], 1).astype(np.float32)),
                "cell_views": pad(count.astype(np.int32)),
                "valid": pad(count > 0, False),
                "cell_x": pad((gx * s).astype(np.int32)),
                "cell_y": pad((gy * s).astype(np.int32)),
                "total": max(1, int(tissue.sum())),
                "grid": (big_h, big_w),
                "slide_grid": (gh, gw),
            }
            if instances:
                cy, cx = np.divmod(cell[tissue], gw)
                row.update(instances=feats[tissue].astype(np.float32), instance_cell=(cy * big_w + cx).astype(np.int64))
            out.append(row)
        return out

    def init_memory(self, env, state, params) -> GlimpseMemory:
        c = self.num_cells(params)
        zero = jnp.zeros((), jnp.int32)
        return GlimpseMemory(
            revealed=jnp.zeros((c,), bool),
            views_read=zero,
            fields=zero,
            over_budget=jnp.zeros((), bool),
            slots=params.mode_data.slots_zero if env.step_obs else None,
            slot_summaries=(
                jnp.zeros(
                    params.mode_data.slots_zero.shape + params.mode_data.summaries.shape[-1:], summary_dtype(params)
                )
                if env.step_obs
                else None
            ),
        )

    def auto_reset_memory(self, env, done, memory, state, params) -> GlimpseMemory:
        """A new episode where ``done``. With ``step_obs`` the cells-read list (``slots``, ``slot_summaries``,
        the largest part of the memory) is not cleared: only its first ``fields`` slots count (the observation
        shows the others empty), so a new episode writes the read flags and counts, not the list."""
        if not env.step_obs:
            return super().auto_reset_memory(env, done, memory, state, params)
        zero = jnp.zeros((), jnp.int32)
        return memory.replace(
            revealed=memory.revealed & ~done,
            views_read=jnp.where(done, zero, memory.views_read),
            fields=jnp.where(done, zero, memory.fields),
            over_budget=memory.over_budget & ~done,
        )

    def apply(self, env, state, action, params) -> Move:
        tables, mem, i = params.mode_data, state.memory, state.slide_index
        c = self.num_cells(params)
        a = jnp.asarray(action, jnp.int32)
        cell = jnp.clip(a, 0, c - 1)
        picked = (a >= 0) & (a < c) & tables.valid[i, cell]
        new = picked & ~mem.revealed[cell]
        n = tables.cell_views[i, cell]
        fits = mem.views_read + n <= budget_views(tables, i)
        slots = mem.slots
        if slots is not None:  # episode_tables: the cell must also find a slot in the cells-read list
            fits = fits & (mem.fields < slots.shape[0])
        reveal = new & fits
        slot_summaries = mem.slot_summaries
        if slots is not None:  # the new cell and its summary go to the next slot (one row, not the whole list)
            j = jnp.minimum(mem.fields, slots.shape[0] - 1)
            slots = slots.at[mem.fields].set(jnp.where(reveal, cell, slots[j]), mode="drop")
            slot_summaries = slot_summaries.at[mem.fields].set(
                jnp.where(reveal, tables.summaries[i, cell].astype(slot_summaries.dtype), slot_summaries[j]),
                mode="drop",
            )
        memory = GlimpseMemory(
            revealed=mem.revealed.at[cell].set(mem.revealed[cell] | reveal),
            views_read=mem.views_read + jnp.where(reveal, n, 0),
            fields=mem.fields + reveal.astype(jnp.int32),
            over_budget=mem.over_budget | (new & ~fits),
            slots=slots,
            slot_summaries=slot_summaries,
        )
        z = jnp.where(picked, self.level, state.z).astype(jnp.int32)
        x = jnp.where(picked, tables.cell_x[i, cell], state.x).astype(jnp.int32)
        y = jnp.where(picked, tables.cell_y[i, cell], state.y).astype(jnp.int32)
        diagnosis = jnp.where(a == c + 1, 1, jnp.where(a == c, 0, -1)).astype(jnp.int32)
        return Move(z, x, y, diagnosis, _declared_score(diagnosis), memory)

    def budget_spent(self, env, state, params) -> jax.Array:
        mem = state.memory
        return mem.over_budget | (mem.views_read >= budget_views(params.mode_data, state.slide_index))

    def memory_obs(self, env, state, params) -> dict:
        tables, mem, i = params.mode_data, state.memory, state.slide_index
        if env.step_obs:
            return self._step_obs(state, tables)
        revealed = mem.revealed.astype(jnp.float32)
        # the product rounded on its own before the subtraction (a min between them: XLA's CPU backend would
        # otherwise fuse them into one multiply-subtract, whose rounding depends on what else the program holds)
        fraction = jnp.minimum(mem.views_read.astype(jnp.float32) * tables.inv_total[i], 1.0)
        return {
            "cells": tables.cells[i],
            "valid": tables.valid[i].astype(jnp.float32),
            "revealed": revealed,
            "summaries": tables.summaries[i] * revealed[:, None],
            "budget_left": jnp.clip(tables.read_budget - fraction, 0.0, 1.0).astype(jnp.float32),
        }

    def _step_obs(self, state, tables) -> dict:
        """The ``episode_tables`` observation's entries (see the module doc)."""
        mem, i = state.memory, state.slide_index
        fraction = jnp.minimum(mem.views_read.astype(jnp.float32) * tables.inv_total[i], 1.0)
        used = jnp.arange(mem.slots.shape[0]) < mem.fields  # slots past ``fields`` may hold an earlier episode's
        return {
            "slide": jnp.asarray(i, jnp.int32),
            "read_bits": pack_bits(mem.revealed),
            "read_cells": jnp.where(used, mem.slots, tables.slots_zero),
            "read_summaries": jnp.where(
                used[:, None],
                mem.slot_summaries,  # kept in the memory: no gather per step
                jnp.zeros((), mem.slot_summaries.dtype),
            ),
            "budget_left": jnp.clip(tables.read_budget - fraction, 0.0, 1.0).astype(jnp.float32),
        }

    @staticmethod
    def num_cells_of(tables) -> int:
        return int(tables.valid.shape[-1])

    def episode_tables(self, env, params) -> dict:
        """What is fixed for a slide during an episode, per slide ``S`` (padded cells ``C``), for a policy
        to index with the observation's ``slide`` (see the module doc): ``cells (S, C, D)`` float32
        low-resolution features, ``valid (S, C)`` float32 0/1, ``cost (S, C)`` float32 the fraction of
        the slide's tissue views that reading the cell reads, ``position (S, C, 2)`` float32 the cell's
        centre ``(x, y)`` over the slide's own grid, in ``[0, 1]``, and ``summaries (S, C, 2D)`` in the feature
        bank's dtype: what a step observation's ``read_summaries`` shows for the cell once it is read."""
        t = params.mode_data
        c = t.valid.shape[-1]
        gy, gx = jnp.divmod(jnp.arange(c), t.grid[1])
        rows, cols = t.slide_grid[:, 0:1].astype(jnp.float32), t.slide_grid[:, 1:2].astype(jnp.float32)
        pos = jnp.stack([(gx[None] + 0.5) / cols, (gy[None] + 0.5) / rows], -1)
        return {
            "cells": t.cells,
            "valid": t.valid.astype(jnp.float32),
            "cost": (t.cell_views.astype(jnp.float32) * t.inv_total[:, None]),
            "position": jnp.clip(pos, 0.0, 1.0).astype(jnp.float32),
            "summaries": t.summaries.astype(summary_dtype(params)),
        }

    def memory_space(self, env, params) -> dict:
        c, d = self.num_cells(params), int(params.mode_data.cells.shape[-1])
        box = lambda shape, lo=-jnp.inf, hi=jnp.inf: spaces.Box(lo, hi, shape, jnp.float32)  # noqa: E731
        if env.step_obs:
            k = int(params.mode_data.slots_zero.shape[0])
            return {
                "slide": spaces.Discrete(int(params.mode_data.valid.shape[0])),
                "read_bits": spaces.Box(np.uint32(0), np.uint32(2**32 - 1), (bit_words(c),), jnp.uint32),
                "read_cells": spaces.Box(0, c, (k,), jnp.int32),
                "read_summaries": spaces.Box(-jnp.inf, jnp.inf, (k, 2 * d), summary_dtype(params)),
                "budget_left": box((), 0.0, 1.0),
            }
        return {
            "cells": box((c, d)),
            "valid": box((c,), 0.0, 1.0),
            "revealed": box((c,), 0.0, 1.0),
            "summaries": box((c, 2 * d)),
            "budget_left": box((), 0.0, 1.0),
        }

    def reading_info(self, env, state, params) -> dict:
        mem, tables = state.memory, params.mode_data
        fraction = mem.views_read.astype(jnp.float32) * tables.inv_total[state.slide_index]
        return {"fraction_read": fraction, "fields_of_view": mem.fields}


def cell_summaries(feats: np.ndarray, cell: np.ndarray, n: int):
    """Host, vectorised: ``(mean (n, D) float64, max (n, D) float64, count (n,) int64)`` of the rows
    ``feats (V, D)`` grouped by ``cell (V,)`` in ``[0, n)`` (0 for a cell without rows). The sums
    run in the rows' order (``np.bincount``), as ``np.add.at`` would add them."""
    v, d = feats.shape
    count = np.bincount(cell, minlength=n)
    flat = (cell[:, None] * d + np.arange(d)[None, :]).reshape(-1)
    mean = np.bincount(flat, weights=feats.reshape(-1).astype(np.float64), minlength=n * d).reshape(n, d)
    mean /= np.maximum(count, 1)[:, None]
    mx = np.zeros((n, d), np.float64)
    if v:
        order = np.argsort(cell, kind="stable")
        starts = np.flatnonzero(np.r_[True, np.diff(cell[order]) != 0])
        mx[cell[order][starts]] = np.maximum.reduceat(feats[order].astype(np.float64), starts, axis=0)
    return mean, mx, count


def summary_dtype(params):
    """The dtype of a step observation's ``read_summaries``: the feature bank's (float16 for the C16
    datasets: the max half exact, the mean rounded to the precision the features are stored at)."""
    return jnp.dtype(params.slide.features.dtype)


def bit_words(n: int) -> int:
    """uint32 words holding ``n`` bits (≥ 1)."""
    return max(1, (int(n) + 31) // 32)


def pack_bits(flags: jax.Array) -> jax.Array:
    """``(n,)`` bool → ``(⌈n/32⌉,)`` uint32, bit ``j % 32`` of word ``j // 32`` is ``flags[j]``."""
    n = flags.shape[-1]
    words = bit_words(n)
    padded = jnp.zeros((words * 32,), jnp.uint32).at[:n].set(flags.astype(jnp.uint32))
    return (padded.reshape(words, 32) << jnp.arange(32, dtype=jnp.uint32)).sum(-1, dtype=jnp.uint32)


def unpack_bits(words: jax.Array, n: int) -> jax.Array:
    """``(..., ⌈n/32⌉)`` uint32 → ``(..., n)`` bool (the inverse of :func:`pack_bits`)."""
    bits = (words[..., :, None] >> jnp.arange(32, dtype=jnp.uint32)) & jnp.uint32(1)
    return bits.reshape(*words.shape[:-1], -1)[..., :n].astype(bool)


def observation_bytes(env, params) -> int:
    """Bytes of one observation of ``env`` (all leaves of its observation space)."""
    space = env.observation_space(params)
    leaves = space.spaces.values() if hasattr(space, "spaces") else [space]
    return int(sum(np.prod(s.shape, dtype=np.int64) * np.dtype(s.dtype).itemsize for s in leaves))


def _to_padded(a: np.ndarray, h: int, w: int, fill) -> np.ndarray:
    """``(gh, gw, …)`` → ``(h·w, …)`` padded with ``fill`` to an ``h × w`` grid."""
    out = np.full((h, w) + a.shape[2:], fill, dtype=a.dtype)
    out[: a.shape[0], : a.shape[1]] = a
    return out.reshape((h * w,) + a.shape[2:])
