"""The reader networks over a set of cells (flax.linen), apart from the navigator networks of
:mod:`baselines.networks`: the policies of ``glimpse`` with ``step_obs=True`` (the ``-v2`` ids).

* :class:`EpisodeTables` — an env's per-slide cell tables, the valid cells packed once on the host.
* :class:`CellEncoder` — the per-cell layers shared by all cells (keys, read slots) and the pooled context; given
  observations they run over the valid cells of the batch's slides only.
* :class:`CellSetActorCritic` — a pointer over the cells (one logit per cell, its key against a query from the
  context) + the two declaring actions + a value; :class:`RecurrentCellSetActorCritic` — the same with a GRU
  (:class:`baselines.networks.ScannedGRU`) over the context.

Their parameters do not depend on the number of cells: one policy runs on any slide size and any dataset. A
rollout with fixed parameters computes their per-cell tables once (``KEYS_ONLY``: the arguments after ``params``
of the call that returns only those tables; :func:`baselines.networks.rollout_apply` /
:func:`~baselines.networks.rollout_step`).
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from baselines.networks import ScannedGRU


class EpisodeTables:
    """The per-slide tables of an env (:meth:`histojax.core.env.HistoEnv.episode_tables`: ``cells (S, C, D)``,
    ``valid``, ``cost`` ``(S, C)``, ``position (S, C, 2)``, ``summaries (S, C, 2D)``) held by a cell-set network,
    which indexes them with the observation's ``slide``. Compared and hashed by identity (a flax module attribute
    must hash; what the network reads travels into the jitted program as constants of the network).

    A padded grid is mostly padding and off-tissue cells (on the C16 set 105 valid cells of 1,330 a slide on
    average), so the valid cells of all slides are packed here, once, on the host, into one flat list of ``N``
    cells in slide order (``flat``: each cell's fixed inputs, ``N`` rows); a network computes its per-cell layers
    over these ``N`` rows only, never over the ``S × C`` grid or the ``S × V`` padded lists."""

    def __init__(self, tables: dict):
        self.tables = {k: jnp.asarray(v) for k, v in tables.items()}
        valid = np.asarray(self.tables["valid"]) > 0  # (S, C)
        s, c = valid.shape
        counts = valid.sum(1)
        n = int(counts.sum())
        start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int32)
        slide_of, cell_of = np.nonzero(valid)  # row-major: slide order, cells ascending
        local = np.arange(n) - start[slide_of]  # each valid cell's entry in its slide's list
        packed = np.full((s, max(1, int(counts.max()))), c, np.int32)
        packed[slide_of, local] = cell_of
        flat = {
            "cells": np.asarray(self.tables["cells"], np.float32)[slide_of, cell_of],
            "cost": np.asarray(self.tables["cost"], np.float32)[slide_of, cell_of],
            "position": np.asarray(self.tables["position"], np.float32)[slide_of, cell_of],
            "summaries": np.asarray(self.tables["summaries"], np.float32)[slide_of, cell_of],
        }
        self.flat = {k: jnp.asarray(v) for k, v in flat.items()}  # (N, ...) each valid cell's fixed inputs
        self.flat_slide = jnp.asarray(slide_of.astype(np.int32))  # (N,) its slide
        self.inv_count = jnp.asarray(1.0 / np.maximum(counts, 1), jnp.float32)  # (S,) 1 / valid cells of the slide
        self.valid_cells = jnp.asarray(packed)  # (S, V) int32 cell index of each packed entry; C = none
        rows = np.full(packed.shape, n, np.int32)
        rows[slide_of, local] = np.arange(n)
        self.packed_rows = jnp.asarray(rows)  # (S, V) flat row of each entry; N = none
        cell_rows = np.full((s, c), n, np.int32)
        cell_rows[slide_of, cell_of] = np.arange(n)
        self.cell_rows = jnp.asarray(cell_rows)  # (S, C) flat row of each cell; N = none
        self.num_flat = n
        self.flat_start = jnp.asarray(start)  # (S,) flat row of each slide's first cell
        self.counts = jnp.asarray(counts.astype(np.int32))  # (S,) valid cells of each slide
        self.flat_slide_none = jnp.asarray(np.append(slide_of, s).astype(np.int32))  # (N + 1,) row N: slide S
        self._inputs = {}

    def row_inputs(self, obs_norm) -> tuple:
        """The per-cell layers' inputs of the ``N`` valid cells and a zero row ``N`` (float32, normalised by
        ``obs_norm``, computed once on the host per ``obs_norm``): ``(fixed (N + 1, F)`` — features, 1, cost × 10,
        position —, ``summary means (N + 1, D)``, ``summary maxima (N + 1, D))``."""
        key = None if obs_norm is None else tuple(np.asarray(a, np.float32).tobytes() for a in obs_norm)
        if key not in self._inputs:

            def norm(x):
                if obs_norm is None:
                    return x
                return (x - np.asarray(obs_norm[0], np.float32)) / np.asarray(obs_norm[1], np.float32)

            f = {k: np.asarray(v, np.float32) for k, v in self.flat.items()}
            n = self.num_flat
            fixed = np.concatenate(
                [norm(f["cells"]), np.ones((n, 1), np.float32), f["cost"][:, None] * np.float32(10.0), f["position"]],
                -1,
            )
            d = f["summaries"].shape[-1] // 2
            parts = (fixed, norm(f["summaries"][:, :d]), norm(f["summaries"][:, d:]))
            self._inputs[key] = tuple(np.concatenate([p, np.zeros((1, p.shape[1]), np.float32)]) for p in parts)
        return tuple(jnp.asarray(a) for a in self._inputs[key])  # numpy held: a traced program takes them as constants

    def __getitem__(self, key):
        return self.tables[key]


NEG = -1e9  # the logit of a cell the policy may not pick (invalid, padding, already read)
CELL_CHUNK = 512  # rows of one block of the per-cell layers over a batch's slides (CellEncoder.batch_tables)


def uses_cell_sets(env) -> bool:
    """True for an env whose reading mode observes steps apart from per-episode tables (``step_obs=True``,
    the ``-v2`` ids, with ``glimpse``): its policies are :class:`CellSetActorCritic` /
    :class:`RecurrentCellSetActorCritic`, which run on any slide size."""
    return bool(getattr(env, "step_obs", False)) and bool(env.episode_tables())


class SplitDense(nn.Module):
    """A dense layer over the concatenation of several inputs (``kernel (F1 + F2 + …, n)``, ``bias (n,)``: the
    parameters of ``nn.Dense`` over the concatenated input, initialised alike), applied part by part:
    ``Σ_j x_j @ kernel[rows of part j] + bias``, so that each part can be computed where it is cheapest."""

    features: int
    kernel_init: object = nn.initializers.orthogonal(np.sqrt(2))

    @nn.compact
    def __call__(self, *parts):
        sizes = [int(p.shape[-1]) for p in parts]
        kernel = self.param("kernel", self.kernel_init, (sum(sizes), self.features), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), jnp.float32)
        out, at = bias, 0
        for p, size in zip(parts, sizes):
            out = out + jnp.asarray(p, jnp.float32) @ kernel[at : at + size]
            at += size
        return out


def cell_layers(p: dict, fixed, means, maxima):
    """The per-cell layers of :class:`CellEncoder` over rows of their inputs (``fixed (R, F)``, ``means``,
    ``maxima (R, D)``, as :meth:`EpisodeTables.row_inputs`) with its parameters ``p`` (``cell_in``, ``cell_mid``,
    ``slot_in``: each ``{"kernel", "bias"}``): ``(keys (R, Hc), slot rows (R, Hc))``, the same operations in the
    same order as the modules."""
    keys = nn.relu(fixed @ p["cell_in"]["kernel"] + p["cell_in"]["bias"])
    keys = nn.relu(keys @ p["cell_mid"]["kernel"] + p["cell_mid"]["bias"])
    k, d = p["slot_in"]["kernel"], means.shape[-1]
    slot = p["slot_in"]["bias"] + means @ k[:d]
    slot = slot + maxima @ k[d : 2 * d]
    return keys, slot + keys @ k[2 * d :]


def _chunks(order, n, chunk: int):
    """``(trips (), rows of trip k)``: the ``n`` live entries of ``order`` in blocks of ``chunk``."""

    def rows(k):
        return jax.lax.dynamic_slice(order, (k * chunk,), (chunk,)), (k * chunk + jnp.arange(chunk)) < n

    return rows


def _gathered_forward(p, inputs, order, n, chunk: int):
    hc = p["cell_mid"]["kernel"].shape[-1]
    rows = _chunks(order, n, chunk)

    def body(carry):
        k, keys_out, slot_out = carry
        r, live = rows(k)
        keys, slot = cell_layers(p, *(a[r] for a in inputs))
        keys_out = jax.lax.dynamic_update_slice(keys_out, jnp.where(live[:, None], keys, 0.0), (k * chunk, 0))
        slot_out = jax.lax.dynamic_update_slice(slot_out, jnp.where(live[:, None], slot, 0.0), (k * chunk, 0))
        return k + 1, keys_out, slot_out

    zero = jnp.zeros((order.shape[0], hc), jnp.float32)
    _, keys, slot = jax.lax.while_loop(lambda c: c[0] * chunk < n, body, (jnp.int32(0), zero, zero))
    return keys, slot


@functools.partial(jax.custom_vjp, nondiff_argnums=(4,))
def gathered_cell_layers(p, inputs, order, n, chunk: int):
    """:func:`cell_layers` over the rows ``order[:n]`` of ``inputs`` only (``order (R,)`` int32, ``R`` a multiple
    of ``chunk``, entries past ``n`` anything in range; ``n`` traced): ``(keys (R, Hc), slot rows (R, Hc))``, row
    ``j < n`` that of input row ``order[j]``, rows ``≥ n`` zeros. The work runs in blocks of ``chunk`` rows while
    ``k · chunk < n`` (a ``lax.while_loop``: the cost follows ``n``, not ``R``); the gradient (parameters only)
    recomputes each block in a second such loop. Pure and jittable; under ``vmap`` the trips are the batch's
    largest."""
    return _gathered_forward(p, inputs, order, n, chunk)


def _gathered_fwd(p, inputs, order, n, chunk):
    return _gathered_forward(p, inputs, order, n, chunk), (p, inputs, order, n)


def _gathered_bwd(chunk, res, g):
    p, inputs, order, n = res
    g_keys, g_slot = g
    hc = g_keys.shape[-1]
    rows = _chunks(order, n, chunk)

    def body(carry):
        k, acc = carry
        r, live = rows(k)
        x = tuple(a[r] for a in inputs)
        cot = tuple(
            jnp.where(live[:, None], jax.lax.dynamic_slice(a, (k * chunk, 0), (chunk, hc)), 0.0)
            for a in (g_keys, g_slot)
        )
        _, vjp = jax.vjp(lambda q: cell_layers(q, *x), p)
        (dp,) = vjp(cot)
        return k + 1, jax.tree.map(jnp.add, acc, dp)

    _, dp = jax.lax.while_loop(lambda c: c[0] * chunk < n, body, (jnp.int32(0), jax.tree.map(jnp.zeros_like, p)))
    return dp, None, None, None


gathered_cell_layers.defvjp(_gathered_fwd, _gathered_bwd)


class CellEncoder(nn.Module):
    """Step observation + episode tables → ``((cell keys (B, V, Hc), their cells (B, V)), context input
    (B, F), pickable (B, C) bool)``. One network shared by all cells embeds each valid cell from what is
    fixed for it during an episode (coarse features, validity, cost, position) into a key, and gives each
    cell the pre-activation it would have as a read slot (its summary and its key through ``slot_in``); given
    observations this runs once per call over the valid cells of the slides the batch shows only
    (:meth:`batch_tables`; ``batch_cells=False``: over the ``N`` valid cells of all slides, packed by
    :class:`EpisodeTables`, as ``obs=None`` does; the same numbers), never per env or per padded cell, and each env
    gathers its slide's keys (``V``: the most valid cells of a slide) and its read slots' rows. ``obs=None`` returns those per-cell tables ``(keys (N + 1, Hc), slot rows (N + 1, Hc), the
    slides' mean keys (S, Hc))`` (row ``N``: zeros, for an empty entry) and ``cell_keys=`` takes them back (a
    rollout computes them once per parameter update: :func:`baselines.networks.rollout_apply`). The ``K`` read slots (their cells
    from the observation's ``read_cells``; their summaries are the tables' ``summaries`` of those cells, what the
    observation's ``read_summaries`` holds) are pooled (mean, max); with the slide's mean key, the view entry and
    the budget left they make the context input."""

    hidden: int  # width of the per-cell layers (Hc)
    tables: EpisodeTables
    obs_norm: tuple | None = None
    batch_cells: bool = True  # per-cell layers over the cells of the batch's slides only (see batch_tables)

    def batch_tables(self, slides):
        """The per-cell tables of the slides in a batch only, from this encoder's parameters (bound, not
        initialising): ``slides (B,)`` int32 → ``(keys (R, Hc), slot rows (R, Hc), mean keys (S, Hc), shift (S,))``.
        The valid cells of the slides present (``n`` of the ``N``, in flat order) take rows ``0 … n − 1``
        (:func:`gathered_cell_layers`: the work follows ``n``), row ``N`` is zeros (``R > N``, static); a cell of a
        present slide at flat row ``f`` of slide ``i`` is at row ``f − shift[i]``. Mean keys of slides not present
        are zeros. The same numbers as the tables of all slides (``obs=None``) where a batch reads them."""
        t = self.tables
        s = t.inv_count.shape[0]
        p = self.variables["params"]
        p = {k: p[k] for k in ("cell_in", "cell_mid", "slot_in")}
        chunk = min(CELL_CHUNK, t.num_flat + 1)
        r = -(-(t.num_flat + 1) // chunk) * chunk
        present = jnp.zeros((s,), bool).at[slides].set(True)
        need = present[t.flat_slide]  # (N,)
        n = need.sum(dtype=jnp.int32)
        order = jnp.nonzero(need, size=r, fill_value=t.num_flat)[0].astype(jnp.int32)  # (R,) flat rows, N after n
        keys, slot_rows = gathered_cell_layers(p, t.row_inputs(self.obs_norm), order, n, chunk)
        here = jnp.where(present, t.counts, 0)
        shift = t.flat_start - (jnp.cumsum(here) - here)  # flat row - local row, present slides
        slide_mean = jax.ops.segment_sum(keys, t.flat_slide_none[order], s + 1, indices_are_sorted=True)[:s]
        return keys, slot_rows, slide_mean * t.inv_count[:, None], shift

    @nn.compact
    def __call__(self, obs, cell_keys=None):
        from histojax.reading.modes.glimpse import unpack_bits

        t = self.tables
        batch = cell_keys is None and obs is not None and self.batch_cells and not self.is_initializing()
        if batch:
            keys, slot_rows, slide_mean, shift = self.batch_tables(jnp.asarray(obs["slide"], jnp.int32))
            cell_keys = keys, slot_rows, slide_mean
        dense = lambda n, name: nn.Dense(n, kernel_init=nn.initializers.orthogonal(np.sqrt(2)), name=name)  # noqa: E731
        norm = (
            (lambda x: x)
            if self.obs_norm is None
            # noqa: E731
            else (
                lambda x: (x - jnp.asarray(self.obs_norm[0], jnp.float32)) / jnp.asarray(self.obs_norm[1], jnp.float32)
            )
        )
        valid = t["valid"]  # (S, C)
        s, c = valid.shape
        if cell_keys is None:
            f = t.flat
            n = t.num_flat
            fixed = jnp.concatenate(
                [norm(f["cells"]), jnp.ones((n, 1), jnp.float32), f["cost"][:, None] * 10.0, f["position"]], -1
            )  # (N, F): valid cells only
            keys = nn.relu(dense(self.hidden, "cell_in")(fixed))
            keys = nn.relu(dense(self.hidden, "cell_mid")(keys))  # (N, Hc): every valid cell, once
            slide_mean = jax.ops.segment_sum(keys, t.flat_slide, s, indices_are_sorted=True) * t.inv_count[:, None]
            d = f["summaries"].shape[-1] // 2
            slot_rows = SplitDense(self.hidden, name="slot_in")(
                norm(f["summaries"][:, :d]), norm(f["summaries"][:, d:]), keys
            )  # (N, Hc)
            zero = jnp.zeros((1, self.hidden), jnp.float32)
            keys, slot_rows = jnp.concatenate([keys, zero]), jnp.concatenate([slot_rows, zero])
        else:
            keys, slot_rows, slide_mean = cell_keys
        if obs is None:
            return keys, slot_rows, slide_mean
        i = jnp.asarray(obs["slide"], jnp.int32)
        b = i.shape[0]
        where = jnp.asarray(obs["read_cells"], jnp.int32)  # (B, K), C = empty
        filled = (where < c).astype(jnp.float32)
        key_rows, slot_at = t.packed_rows[i], t.cell_rows[i[:, None], jnp.minimum(where, c - 1)]  # flat rows, N = none
        if batch:  # rows of the batch's tables
            none = t.num_flat
            key_rows = jnp.where(key_rows < none, key_rows - shift[i][:, None], none)
            slot_at = jnp.where(slot_at < none, slot_at - shift[i][:, None], none)
        slots = nn.relu(slot_rows[slot_at])  # (B, K, Hc)
        n_read = filled.sum(-1, keepdims=True)
        # a contraction, not a product then a sum: XLA's CPU backend runs the latter 50x slower at (B, K, Hc)
        slot_mean = jnp.einsum("bk,bkh->bh", filled, slots) / jnp.maximum(n_read, 1.0)
        slot_max = jnp.where(filled[..., None] > 0, slots, 0.0).max(1)
        d = int(jnp.shape(obs["read_summaries"])[-1]) // 2
        view = [
            jnp.asarray(v, jnp.float32).reshape(b, -1)
            for k, v in sorted(obs.items())
            if k not in ("slide", "read_bits", "read_cells", "read_summaries")
        ]
        view = [norm(v) if v.shape[-1] == d else v for v in view]
        context_in = jnp.concatenate([slide_mean[i], slot_mean, slot_max, n_read / where.shape[-1], *view], -1)
        read = unpack_bits(jnp.asarray(obs["read_bits"]), c)  # (B, C) bool
        pickable = (valid[i] > 0) & ~read
        return (keys[key_rows], t.valid_cells[i]), context_in, pickable


def cell_logits(module: nn.Module, keys, context, pickable):
    """Pointer logits: one per cell, the dot product of its key with a query from the context (``(B,
    C)``, ``NEG`` where ``pickable`` is false; ``keys``: the valid cells' keys ``(B, V, Hc)`` and their
    cells ``(B, V)`` (``C``: none), so the cost per env grows as ``V × Hc``), then the 2 declaring
    actions from the context: ``((B, C + 2), value (B,))``."""
    keys, cells = keys
    hc = keys.shape[-1]
    query = nn.Dense(hc, kernel_init=nn.initializers.orthogonal(0.01), name="query")(context)
    packed = jnp.einsum("bvh,bh->bv", keys, query) / np.sqrt(hc)
    rows = jnp.arange(cells.shape[0])[:, None]
    per_cell = jnp.full(pickable.shape, NEG, packed.dtype).at[rows, cells].set(packed, mode="drop")
    per_cell = jnp.where(pickable, per_cell, NEG)
    declare = nn.Dense(
        2, kernel_init=nn.initializers.orthogonal(0.01), bias_init=nn.initializers.zeros, name="declare"
    )(nn.tanh(nn.Dense(module.hidden // 2, name="declare_in")(context)))
    value = nn.Dense(1, kernel_init=nn.initializers.orthogonal(1.0), name="value")(
        nn.tanh(nn.Dense(module.hidden // 2, name="value_in")(context))
    )[..., 0]
    return jnp.concatenate([per_cell, declare], -1), value


class CellSetActorCritic(nn.Module):
    """A reader policy over the set of a slide's cells, for ``glimpse`` with ``step_obs=True``:
    ``__call__(obs) -> (logits (B, C + 2), value (B,))``. A per-cell encoder shared by all cells
    (:class:`CellEncoder`: keys, and the read cells pooled into a context), then a pointer: one logit
    per cell, its key against a query from the context (invalid, padding and already read cells
    masked), and the two declaring actions from the context. Its parameters do not depend on ``C``: one policy runs on any
    slide size and any dataset (build it with that env's tables), and its cost grows with ``C``.
    ``action_dim`` is unused (the env's ``C + 2``), kept so that trainers build it as the others.
    ``apply(params, None)`` gives the per-cell tables (keys, slot rows, slide means: :class:`CellEncoder`), which
    ``apply(params, obs, cell_keys=...)`` takes back (the same outputs; a rollout with fixed parameters computes them once: :func:`baselines.networks.rollout_apply`)."""

    KEYS_ONLY = (None,)  # apply(params, None): the per-cell tables only (rollout_apply computes them once)

    action_dim: int
    tables: EpisodeTables
    action_mode: str = "glimpse"
    hidden: int = 256  # the context's width (config "hidden")
    obs_norm: tuple | None = None
    cell_hidden: int = 32  # the per-cell layers' width (config "cell_hidden")
    batch_cells: bool = True  # given observations, the per-cell layers over their slides' cells only (CellEncoder)

    @nn.compact
    def __call__(self, obs, cell_keys=None):
        encoded = CellEncoder(self.cell_hidden, self.tables, self.obs_norm, self.batch_cells)(obs, cell_keys)
        if obs is None:  # the per-cell tables only (see CellEncoder)
            return encoded
        keys, context_in, pickable = encoded
        context = nn.relu(
            nn.Dense(self.hidden, kernel_init=nn.initializers.orthogonal(np.sqrt(2)), name="context")(context_in)
        )
        return cell_logits(self, keys, context, pickable)


class RecurrentCellSetActorCritic(nn.Module):
    """:class:`CellSetActorCritic` with a GRU over the per-step context (hidden state reset at
    episode starts, as :class:`baselines.networks.RecurrentActorCritic`): ``__call__(h (B, H), obs (T, B, ...), resets
    (T, B)) -> (h_T, logits (T, B, C + 2), value (T, B))``. The pointer's query comes from the GRU's
    output."""

    KEYS_ONLY = (None, None, None)  # apply(params, None, None, None): the per-cell tables only (rollout_step)

    action_dim: int
    tables: EpisodeTables
    action_mode: str = "glimpse"
    hidden: int = 128  # the context's and the GRU's width (config "hidden")
    obs_norm: tuple | None = None
    cell_hidden: int = 32  # the per-cell layers' width (config "cell_hidden")
    batch_cells: bool = True  # given observations, the per-cell layers over their slides' cells only (CellEncoder)

    @nn.compact
    def __call__(self, h, obs, resets, cell_keys=None):
        encoder = CellEncoder(self.cell_hidden, self.tables, self.obs_norm, self.batch_cells)
        if obs is None:  # the per-cell tables only (see CellEncoder)
            return encoder(None, cell_keys)
        t, b = resets.shape
        flat = jax.tree.map(lambda a: jnp.reshape(a, (t * b, *jnp.shape(a)[2:])), obs)
        keys, context_in, pickable = encoder(flat, cell_keys)
        x = nn.relu(
            nn.Dense(self.hidden, kernel_init=nn.initializers.orthogonal(np.sqrt(2)), name="context")(context_in)
        )
        h, y = ScannedGRU(self.hidden)(h, (x.reshape(t, b, -1), resets.astype(bool)))
        logits, value = cell_logits(self, keys, y.reshape(t * b, -1), pickable)
        return h, logits.reshape(t, b, -1), value.reshape(t, b)
