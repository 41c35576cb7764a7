"""A slide head with spatial context: one tumour logit for a slide from the finest-level views read so far.

A metastasis spans neighbouring views; an encoder's false positives are mostly isolated. So the head
does not take the plain maximum of the view logits: it first averages each read view's logit with the
read views of its ``k × k`` neighbourhood (views not read, and views off tissue, count for nothing),
then pools the neighbourhood means of the read views (the mean of the ``top`` largest; ``top=1`` is
the maximum), optionally minus the median logit of the read views (a slide-level offset: staining or
tissue type that raises every view), and maps that statistic ``s`` to a slide logit ``cal_a · s + cal_b``
(a logistic calibration fitted on training slides: :mod:`baselines.reading.head_fit`). A slide with nothing
read scores ``prior_logit`` (the training split's log odds of tumour).

Pure JAX and jittable (``jax.jit(heads.score)``, ``jax.vmap`` over slides padded to one grid: padding is
simply never read); no host callbacks, no data-dependent Python control flow::

    from histojax.reading import heads
    head = heads.load("baselines/published/c16-v2-head")      # a LogitHead (its config.json's kind)
    logit = heads.score(head, grid_features, read_mask)      # (H, W, D), (H, W) bool -> () float32

``grid_features`` is the feature grid of the slide's finest level (one row per finest-level view,
``D`` entries; entry ``head.dim`` is the view's tumour logit — pcam-cnn's ``mean l``, entry 62), and
``read_mask`` marks the views read that hold tissue. :meth:`LogitHead.score_logits` takes the ``(H, W)`` logit
map directly. Saved as a folder: ``config.json`` (the head's structure and how it was fitted and chosen)
and ``params.json`` (``a``, ``b``, ``prior_logit``: the calibration's keys in the file are ``a`` and ``b``).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
from flax import struct

from histojax.reading.heads import files

KIND = "neighbourhood-pooled-logit"
FORMAT = 1
MAX_DIM = 1 << 16
"""The largest feature entry a head may read (a 65,536-d encoder)."""
MAX_K = 64
"""The widest neighbourhood side a head may pool, in views (the published head's is 2; a lesion spans a few)."""
MAX_TOP = 1 << 20
"""The most views a head may pool the mean of (``top``)."""
MAX_PARAM = 1e6
"""The largest magnitude of ``cal_a``, ``cal_b`` and ``prior_logit`` read: with view logits in float16's range
(±65,504) ``cal_a · s + cal_b`` stays far inside float32 (a fitted calibration is a few units)."""
MAX_PARAMS_JSON_BYTES = 1 << 16
"""``params.json`` (three numbers) larger than this (64 KiB) is refused unread."""


@struct.dataclass
class LogitHead(files.SavedHead):
    """The neighbourhood-pooled logit head, fitted (a pytree: ``cal_a``, ``cal_b``, ``prior_logit`` are leaves;
    the structure is static).

    ``dim``: feature entry of the view tumour logit; ``k``: neighbourhood side in views (1 = none);
    ``top``: pool the mean of the ``top`` largest neighbourhood means; ``minus_median``: subtract the
    read views' median logit; ``cal_a``, ``cal_b``: calibration (slide logit = ``cal_a · s + cal_b``, as in
    every head; ``params.json`` keeps them as ``a`` and ``b``); ``prior_logit``:
    the score of a slide with nothing read; ``info``: a JSON object (text) recording the fit, merged into config.json."""

    cal_a: jnp.ndarray = 1.0
    cal_b: jnp.ndarray = 0.0
    prior_logit: jnp.ndarray = 0.0
    dim: int = struct.field(pytree_node=False, default=62)
    k: int = struct.field(pytree_node=False, default=3)
    top: int = struct.field(pytree_node=False, default=1)
    minus_median: bool = struct.field(pytree_node=False, default=False)
    encoder: str | None = struct.field(pytree_node=False, default="pcam-cnn")
    info: str = struct.field(pytree_node=False, default="{}")

    @property
    def name(self) -> str:
        """A short name of the structure, e.g. ``"3x3 mean, max"`` or ``"2x2 mean, top-3, minus median"``."""
        parts = [
            f"{self.k}x{self.k} mean" if self.k > 1 else "view logit",
            "max" if self.top == 1 else f"top-{self.top}",
        ]
        return ", ".join(parts + (["minus median"] if self.minus_median else []))

    def structure(self) -> dict:
        """The structure entries of ``config.json`` (:meth:`files.SavedHead.config`)."""
        return {"dim": int(self.dim), "k": int(self.k), "top": int(self.top), "minus_median": bool(self.minus_median)}

    def save(self, folder) -> Path:
        """Write ``folder/params.json`` (``a``, ``b``: the calibration's keys in the file; ``prior_logit``) and
        ``folder/config.json``; returns the folder."""
        params = {"a": float(self.cal_a), "b": float(self.cal_b), "prior_logit": float(self.prior_logit)}
        return self.write(folder, "params.json", files.json_text(params).encode())

    kind = KIND
    FORMAT = FORMAT

    def view_logits(self, grid_features: jax.Array) -> jax.Array:
        """The per-view scores the head pools: ``(H, W)`` tumour logits, entry ``dim`` of ``(H, W, D)`` features.
        ``ValueError`` (one line, at trace time) when ``dim`` ≥ ``D``: never a clamped, other entry."""
        grid_features = jnp.asarray(grid_features)
        check_dim(self, grid_features.shape[-1])
        return grid_features[..., self.dim]

    def score_logits(self, logits: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Slide tumour logit ``()`` float32 from a ``(H, W)`` view-logit map and the read mask ``(H, W)`` bool."""
        s = statistic(self, logits, read_mask)
        return jnp.where(jnp.any(read_mask), self.cal_a * s + self.cal_b, self.prior_logit).astype(jnp.float32)

    def score(self, grid_features: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Slide tumour logit ``()`` float32 from the finest-level feature grid ``(H, W, D)`` and the read
        tissue views ``(H, W)`` bool (entry ``dim`` of each view is its tumour logit)."""
        return self.score_logits(self.view_logits(grid_features), read_mask)

    @classmethod
    def load(cls, folder) -> "LogitHead":
        """Read a head saved by :meth:`save` through the guarded reader (:mod:`histojax.reading.heads.files`:
        regular files of bounded size, bounded JSON nesting, strict types): ``kind`` this one, ``format``
        :data:`FORMAT`, ``dim`` an int in ``[0, MAX_DIM]``, ``k`` in ``[1, MAX_K]``, ``top`` in ``[1, MAX_TOP]``,
        ``minus_median`` a JSON bool, ``params.json``'s ``a``, ``b`` (read as ``cal_a``, ``cal_b``) and ``prior_logit``
        (and nothing else) finite with magnitude at most :data:`MAX_PARAM` (so the slide logit stays finite in
        float32). ``ValueError``
        (:class:`~histojax.reading.heads.files.HeadFileError`) naming the file, one line, on anything else."""
        folder = Path(folder)
        cfg_file, par_file = folder / files.CONFIG, folder / "params.json"
        cfg = files.read_config(cfg_file)
        if cfg.get("kind") != KIND:
            raise files.HeadFileError(
                cfg_file, f"not a slide head config (kind {cfg.get('kind')!r}, expected {KIND!r})"
            )
        fmt = files.field(cfg, "format", int, cfg_file)
        if fmt != FORMAT:
            raise files.HeadFileError(cfg_file, f"{KIND} head format {fmt}; this version reads format {FORMAT}")
        dim = files.field(cfg, "dim", int, cfg_file, lo=0, hi=MAX_DIM)
        k = files.field(cfg, "k", int, cfg_file, lo=1, hi=MAX_K)
        top = files.field(cfg, "top", int, cfg_file, lo=1, hi=MAX_TOP)
        minus_median = files.field(cfg, "minus_median", bool, cfg_file, default=False)
        encoder = files.field(cfg, "encoder", (str, type(None)), cfg_file, default=None)
        par = files.read_config(par_file, max_bytes=MAX_PARAMS_JSON_BYTES, what="parameters")
        a, b, prior = (
            files.field(par, n, float, par_file, lo=-MAX_PARAM, hi=MAX_PARAM) for n in ("a", "b", "prior_logit")
        )
        unknown = sorted(set(par) - {"a", "b", "prior_logit"})
        if unknown:  # a typo or another tool's parameter would otherwise be ignored without a word
            raise files.HeadFileError(
                par_file,
                f"unknown entry {unknown[0]!r} (a {KIND} head's parameters are "
                "a, b and prior_logit); remove it or refit the head",
            )
        known = {"kind", "format", "dim", "k", "top", "minus_median", "encoder", "name", "input", "output"}
        info = json.dumps({key: v for key, v in cfg.items() if key not in known})  # json-not-written: save writes it
        return cls(
            cal_a=jnp.float32(a),
            cal_b=jnp.float32(b),
            prior_logit=jnp.float32(prior),
            dim=dim,
            k=k,
            top=top,
            minus_median=minus_median,
            encoder=encoder,
            info=info,
        )


def check_dim(head, d: int) -> None:
    """Refuse (``ValueError``, one line) to read feature entry ``head.dim`` from features of ``d`` entries when
    ``head.dim >= d`` (JAX indexing would clamp it to entry ``d - 1`` without a word): a head fitted on another
    encoder's features."""
    if not 0 <= int(head.dim) < int(d):
        raise ValueError(
            f"this slide head ({head.kind}, {head.name}) reads feature entry {head.dim} "
            f"(its encoder {head.encoder!r}), but the features have {d} entries (0..{d - 1}): it was "
            "fitted on another encoder's features; use a head fitted on these features"
        )


def neighbourhood_mean(logits: jax.Array, mask: jax.Array, k: int) -> jax.Array:
    """``(H, W)`` mean of ``logits`` over the ``mask``-ed views of each view's ``k × k`` neighbourhood
    (window centred on the view; for even ``k`` it reaches one view further down / right); 0 where no
    masked view is in reach."""
    m = mask.astype(jnp.float32)
    x = jnp.where(mask, logits.astype(jnp.float32), 0.0)
    if k == 1:
        return x
    pad = ((k - 1) // 2, k // 2)

    def box(a):  # a k × k box sum, separably: k rows, then k columns (2k adds a view, not k²)
        a = jax.lax.reduce_window(a, 0.0, jax.lax.add, (k, 1), (1, 1), (pad, (0, 0)))
        return jax.lax.reduce_window(a, 0.0, jax.lax.add, (1, k), (1, 1), ((0, 0), pad))

    return box(x) / jnp.maximum(box(m), 1.0)


def statistic(head: LogitHead, logits: jax.Array, mask: jax.Array) -> jax.Array:
    """The head's pooled statistic ``s`` (before calibration) of a ``(H, W)`` logit map over the read
    views ``mask (H, W)`` bool; ``-inf``-free: 0 when nothing is read (see :meth:`LogitHead.score_logits`)."""
    mask = jnp.asarray(mask, bool)
    nb = neighbourhood_mean(logits, mask, head.k).reshape(-1)
    flat = mask.reshape(-1)
    n = flat.sum()
    vals = jnp.where(flat, nb, -jnp.inf)
    top = min(head.top, vals.shape[0])
    best = jax.lax.top_k(vals, top)[0]
    take = jnp.arange(top) < n  # fewer views read than `top`: the mean of those there are
    s = jnp.where(take, best, 0.0).sum() / jnp.maximum(jnp.minimum(n, top), 1)
    if head.minus_median:
        s = s - jnp.nanmedian(jnp.where(flat, logits.reshape(-1).astype(jnp.float32), jnp.nan))
    return jnp.where(n > 0, s, 0.0)


statistic_batch = jax.jit(jax.vmap(statistic, in_axes=(None, 0, 0)))
"""Jitted :func:`statistic` over a batch ``(B, H, W)``, ``(B, H, W)`` → ``(B,)``."""
