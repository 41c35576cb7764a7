"""Trained slide heads beside :class:`histojax.reading.heads.logit.LogitHead`: an attention-MIL over neighbourhood-pooled
views (:class:`MilHead`) and a logistic model of pooled statistics (:class:`StatsHead`).

Both score a slide from what has been read, with the protocol of :mod:`histojax.reading.heads` (they are what
``heads.load`` returns for a folder of their kind, and ``heads.score`` / ``heads.score_logits`` call their
methods), so the readers, ``HeadReward`` and the diagnosis tools use them unchanged::

    from histojax.reading import heads
    head = heads.load("baselines/published/c16-v2-head-mil")
    logit = heads.score(head, grid_features, read_mask)      # (H, W, D), (H, W) bool -> () float32

:func:`attention_pool` is the one gated-attention MIL of the project: the baselines' "read everything"
classifier (:mod:`baselines.reading.budget_curve`) trains the same pooling.

**Instances.** Each read view is described by the ``k × k`` neighbourhood means of the view tumour logit
(feature entry ``dim``) over the *read* views, for ``k`` in ``ks`` (:func:`histojax.reading.heads.logit.neighbourhood_mean`,
views not read count for nothing); with ``inputs="features"`` also the ``feature_k × feature_k``
neighbourhood mean of all ``D`` feature entries (such a head needs the whole grid: ``score``, not
``score_logits``).

**MilHead** (gated attention, Ilse et al. 2018 / CLAM): standardised instance ``x`` → ``h = relu(W₁x + b₁)``
(``hidden`` units) → attention ``a = wₐ · (tanh(V h) ⊙ σ(U h))`` → softmax of ``a`` over the read views only
→ ``z = Σ softmax(a) h`` → slide logit ``w_c · z + b_c``.

**StatsHead**: the statistics of :func:`statistics_of` (top-1 and top-3 means of each neighbourhood mean,
counts of 2 × 2 means above thresholds, the number of views read), standardised, then ``w · s + b``.

A slide with nothing read scores ``prior_logit``. Pure JAX, jittable, vmappable over slides padded to one
grid (padding is never read). Fitted by :mod:`baselines.reading.head_mil_fit` with random read masks, so they score
partial reads. Saved as a folder: ``config.json`` (``kind``, ``format``, structure, the fit) and
``params.npz`` (the arrays).
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from histojax.reading.heads import files
from histojax.reading.heads.logit import MAX_DIM, MAX_K, check_dim, neighbourhood_mean

KIND_MIL = "attention-mil"
KIND_STATS = "pooled-statistics"
KINDS = (KIND_MIL, KIND_STATS)
FORMAT = 1
THRESHOLDS = (0.0, 1.0, 2.0)  # view-logit thresholds of the counts in StatsHead's statistics
TOPS = (1, 3)
MAX_UNITS = 4096
"""The most hidden or attention units a MIL head may have."""
MIN_SD = 1e-7
"""The smallest standardisation ``sd`` read (the fits add 1e-6 or 1e-3 to every standard deviation)."""


def logit_instances(logits: jax.Array, mask: jax.Array, ks) -> jax.Array:
    """``(H, W, len(ks))``: for each view the ``k × k`` neighbourhood mean of ``logits`` over the read views
    ``mask``, one channel per ``k`` in ``ks`` (0 where nothing in reach is read)."""
    mask = jnp.asarray(mask, bool)
    return jnp.stack([neighbourhood_mean(logits, mask, int(k)) for k in ks], -1)


def feature_means(features: jax.Array, mask: jax.Array, k: int) -> jax.Array:
    """``(H, W, D)`` the ``k × k`` neighbourhood mean of every feature entry over the read views (the window of
    :func:`histojax.reading.heads.logit.neighbourhood_mean`)."""
    m = jnp.asarray(mask, bool).astype(jnp.float32)
    x = jnp.where(mask[..., None], features.astype(jnp.float32), 0.0)
    if k == 1:
        return x
    pad = ((k - 1) // 2, k // 2)

    def box(a):
        extra = ((0, 0),) * (a.ndim - 2)
        a = jax.lax.reduce_window(
            a, 0.0, jax.lax.add, (k, 1) + (1,) * (a.ndim - 2), (1,) * a.ndim, (pad, (0, 0)) + extra
        )
        return jax.lax.reduce_window(
            a, 0.0, jax.lax.add, (1, k) + (1,) * (a.ndim - 2), (1,) * a.ndim, ((0, 0), pad) + extra
        )

    return box(x) / jnp.maximum(box(m), 1.0)[..., None]


def _gated(params: dict, x: jax.Array, mask: jax.Array, seg: jax.Array, num_segments: int):
    """``(h (N, hidden), e (N,), den (num_segments,))``: the instances' hidden units, their unnormalised attention
    ``exp(a - max a of the bag)`` (0 where not read) and each bag's sum of it."""
    xs = (x - params["mu"]) / params["sd"]
    h = jax.nn.relu(xs @ params["w1"] + params["b1"])
    gate = jnp.tanh(h @ params["V"] + params["bV"]) * jax.nn.sigmoid(h @ params["U"] + params["bU"])
    a = jnp.where(mask, gate @ params["wa"], -jnp.inf)
    amax = jax.ops.segment_max(a, seg, num_segments)
    amax = jnp.where(jnp.isfinite(amax), amax, 0.0)
    e = jnp.where(mask, jnp.exp(a - amax[seg]), 0.0)
    return h, e, jax.ops.segment_sum(e, seg, num_segments)


def attention_pool(
    params: dict, x: jax.Array, mask: jax.Array, segments: jax.Array | None = None, num_segments: int = 1
) -> jax.Array:
    """Gated-attention MIL over instances ``x (N, F)`` read where ``mask (N,)``; ``segments (N,)`` int assigns
    instances to bags (default one bag). Returns ``(num_segments,)`` slide logits (0 for a bag with nothing
    read: the caller substitutes the prior). ``params``: ``mu``, ``sd`` ``(F,)`` (standardisation), ``w1 (F, H)``,
    ``b1 (H,)``, ``V``, ``U (H, A)``, ``bV``, ``bU (A,)``, ``wa (A,)``, ``wc (H,)``, ``bc ()``."""
    seg = jnp.zeros(x.shape[0], jnp.int32) if segments is None else segments
    h, e, den = _gated(params, x, mask, seg, num_segments)
    z = jax.ops.segment_sum(e[:, None] * h, seg, num_segments) / jnp.maximum(den, 1e-30)[:, None]
    return z @ params["wc"] + params["bc"]


def attention_weights(
    params: dict, x: jax.Array, mask: jax.Array, segments: jax.Array | None = None, num_segments: int = 1
) -> jax.Array:
    """The attention :func:`attention_pool` gives each instance ``(N,)`` (summing to 1 over a bag's read
    instances, 0 where not read)."""
    seg = jnp.zeros(x.shape[0], jnp.int32) if segments is None else segments
    _, e, den = _gated(params, x, mask, seg, num_segments)
    return e / jnp.maximum(den, 1e-30)[seg]


def statistics_of(logits: jax.Array, mask: jax.Array, ks=(1, 2, 3, 4)) -> jax.Array:
    """StatsHead's statistics ``(len(ks)·len(TOPS) + len(THRESHOLDS) + 1,)`` of a ``(H, W)`` logit map over the
    read views: for each ``k``, the mean of the 1 and 3 largest ``k × k`` neighbourhood means of read views;
    ``log(1 + count)`` of read views whose 2 × 2 mean exceeds each of ``THRESHOLDS``; ``log(1 + views read)``.
    Zeros when nothing is read."""
    mask = jnp.asarray(mask, bool)
    flat = mask.reshape(-1)
    n = flat.sum()
    out = []
    for k in ks:
        vals = jnp.where(flat, neighbourhood_mean(logits, mask, int(k)).reshape(-1), -jnp.inf)
        best = jax.lax.top_k(vals, max(TOPS))[0]
        for t in TOPS:
            take = jnp.arange(t) < n
            out.append(jnp.where(take, best[:t], 0.0).sum() / jnp.maximum(jnp.minimum(n, t), 1))
    m2 = neighbourhood_mean(logits, mask, 2).reshape(-1)
    for t in THRESHOLDS:
        out.append(jnp.log1p(jnp.sum(flat & (m2 > t))))
    out.append(jnp.log1p(n.astype(jnp.float32)))
    s = jnp.stack(out).astype(jnp.float32)
    return jnp.where(n > 0, s, 0.0)


class _Saved(files.SavedHead):
    """Save / load / scoring helpers shared by the two heads (``config.json`` through :class:`files.SavedHead`)."""

    FORMAT = FORMAT

    def save(self, folder) -> Path:
        """Write ``folder/params.npz`` (the arrays and ``prior_logit``, float32) and ``folder/config.json``; returns
        the folder."""
        arrays = {k: np.asarray(v, np.float32) for k, v in self.params.items()}
        arrays["prior_logit"] = np.asarray(self.prior_logit, np.float32)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        return self.write(folder, files.PARAMS, buf.getvalue())

    @classmethod
    def load(cls, folder):
        """Read a head of this class's kind saved by :meth:`save` (:func:`load` reads either kind).
        ``ValueError`` naming the file, one line, on anything malformed or of another kind."""
        head = load(folder)
        if head.kind != cls.kind:
            raise ValueError(f"{Path(folder) / 'config.json'}: a {head.kind} head, not {cls.kind}")
        return head

    def view_logits(self, grid_features: jax.Array) -> jax.Array:
        """The per-view scores the instances are built from: ``(H, W)`` tumour logits, entry ``dim`` of ``(H, W, D)``
        (``ValueError``, one line, when ``dim`` ≥ ``D``: never a clamped, other entry)."""
        grid_features = jnp.asarray(grid_features)
        check_dim(self, grid_features.shape[-1])
        return grid_features[..., self.dim]

    def score(self, grid_features: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Slide tumour logit ``()`` float32 from the feature grid ``(H, W, D)`` and the read views ``(H, W)`` bool."""
        grid_features = jnp.asarray(grid_features)
        return self._score(self.view_logits(grid_features), grid_features, read_mask)

    def score_logits(self, logits: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Slide tumour logit ``()`` float32 from the ``(H, W)`` view-logit map and the read views ``(H, W)`` bool."""
        return self._score(jnp.asarray(logits), None, read_mask)


@struct.dataclass
class MilHead(_Saved):
    """A gated-attention MIL head (see the module doc). ``params``: the arrays (a pytree leaf dict);
    ``prior_logit``: the score of a slide with nothing read; ``dim``: the view-logit entry; ``ks``: logit
    neighbourhood sides of the instances; ``inputs``: ``"logit"`` or ``"features"`` (also the ``feature_k``
    neighbourhood mean of all entries); ``info``: the fit (JSON text, merged into config.json)."""

    params: dict
    prior_logit: jnp.ndarray = 0.0
    dim: int = struct.field(pytree_node=False, default=62)
    ks: tuple = struct.field(pytree_node=False, default=(1, 2, 3, 4))
    inputs: str = struct.field(pytree_node=False, default="logit")
    feature_k: int = struct.field(pytree_node=False, default=2)
    hidden: int = struct.field(pytree_node=False, default=64)
    encoder: str | None = struct.field(pytree_node=False, default="pcam-cnn")
    info: str = struct.field(pytree_node=False, default="{}")
    source: str | None = struct.field(pytree_node=False, default=None)  # the folder loaded from (error lines)
    KIND = KIND_MIL
    kind = KIND_MIL

    @property
    def name(self) -> str:
        """A short name, e.g. ``"attention-MIL over 1-4 logit means"``."""
        what = (
            f"{min(self.ks)}-{max(self.ks)} logit means"
            if len(self.ks) > 1
            else f"{self.ks[0]}x{self.ks[0]} logit mean"
        )
        if self.inputs == "features":
            what += f" + {self.feature_k}x{self.feature_k} feature means"
        return f"attention-MIL over {what}, {self.hidden} units"

    def structure(self) -> dict:
        """The structure entries of ``config.json`` (:meth:`files.SavedHead.config`)."""
        return {
            "dim": self.dim,
            "ks": list(self.ks),
            "inputs": self.inputs,
            "feature_k": self.feature_k,
            "hidden": self.hidden,
        }

    def instances(self, logits, features, mask) -> jax.Array:
        """``(H, W, F)`` the instance vector of each view (meaningful where ``mask``)."""
        x = logit_instances(logits, mask, self.ks)
        if self.inputs == "features":
            if features is None:
                raise ValueError(
                    f"this head ({self.name}) reads all feature entries: call histojax.reading.heads.score with "
                    "the feature grid, not score_logits with the logit map"
                )
            want = self.params["mu"].shape[0] - len(self.ks)
            if features.shape[-1] != want:
                raise ValueError(
                    f"this slide head ({self.name}) reads all {want} feature entries, but the features "
                    f"have {features.shape[-1]}: it was fitted on another encoder's features"
                )
            x = jnp.concatenate([x, feature_means(features, mask, self.feature_k)], -1)
        return x

    def _score(self, logits, features, read_mask) -> jax.Array:
        mask = jnp.asarray(read_mask, bool)
        x = self.instances(logits, features, mask)
        s = attention_pool(self.params, x.reshape(-1, x.shape[-1]), mask.reshape(-1))[0]
        return jnp.where(jnp.any(mask), s, self.prior_logit).astype(jnp.float32)


@struct.dataclass
class StatsHead(_Saved):
    """A logistic model of pooled statistics (:func:`statistics_of`); ``params``: ``mu``, ``sd`` (standardisation)
    and ``w``, ``b``; other fields as :class:`MilHead`."""

    params: dict
    prior_logit: jnp.ndarray = 0.0
    dim: int = struct.field(pytree_node=False, default=62)
    ks: tuple = struct.field(pytree_node=False, default=(1, 2, 3, 4))
    encoder: str | None = struct.field(pytree_node=False, default="pcam-cnn")
    info: str = struct.field(pytree_node=False, default="{}")
    source: str | None = struct.field(pytree_node=False, default=None)  # the folder loaded from (error lines)
    KIND = KIND_STATS
    kind = KIND_STATS

    @property
    def name(self) -> str:
        return f"logistic over pooled statistics ({min(self.ks)}-{max(self.ks)} means, top-1/3, counts, views read)"

    def structure(self) -> dict:
        """The structure entries of ``config.json`` (:meth:`files.SavedHead.config`)."""
        return {"dim": self.dim, "ks": list(self.ks), "thresholds": list(THRESHOLDS), "tops": list(TOPS)}

    def _score(self, logits, features, read_mask) -> jax.Array:
        mask = jnp.asarray(read_mask, bool)
        s = (statistics_of(logits, mask, self.ks) - self.params["mu"]) / self.params["sd"]
        out = s @ self.params["w"] + self.params["b"]
        return jnp.where(jnp.any(mask), out, self.prior_logit).astype(jnp.float32)


MAX_KS = 8
"""The most neighbourhood sides (``ks``) a head's instances may hold."""


def param_shapes(kind: str, n_ks: int, hidden: int | None = None, inputs: str = "logit") -> dict:
    """The arrays of a head's ``params.npz`` (name -> shape; ``None``: any size, the feature dimension of an
    ``inputs="features"`` head, checked against the other arrays after reading)."""
    if kind == KIND_STATS:
        n = n_ks * len(TOPS) + len(THRESHOLDS) + 1
        return {"mu": (n,), "sd": (n,), "w": (n,), "b": (), "prior_logit": ()}
    f = n_ks if inputs == "logit" else None
    return {
        "mu": (f,),
        "sd": (f,),
        "w1": (f, hidden),
        "b1": (hidden,),
        "V": (hidden, None),
        "bV": (None,),
        "U": (hidden, None),
        "bU": (None,),
        "wa": (None,),
        "wc": (hidden,),
        "bc": (),
        "prior_logit": (),
    }


def load(folder):
    """Read a head saved by ``save`` (either kind) through the guarded reader
    (:mod:`histojax.reading.heads.files`: regular files of bounded size, bounded JSON nesting, strict types,
    every ``params.npz`` member's header checked before its data is read, exactly the arrays the config
    implies, floats only, finite). ``ValueError`` (:class:`~histojax.reading.heads.files.HeadFileError`) naming
    the file, one line, on anything malformed or of a kind / format this version does not know."""
    folder = Path(folder)
    cfg_file, par_file = folder / files.CONFIG, folder / files.PARAMS
    cfg = files.read_config(cfg_file)
    kind = cfg.get("kind")
    if kind not in KINDS:
        raise files.HeadFileError(
            cfg_file, f"not a slide head this version reads (kind {kind!r}; known: {', '.join(KINDS)})"
        )
    fmt = files.field(cfg, "format", int, cfg_file)
    if fmt != FORMAT:
        raise files.HeadFileError(cfg_file, f"{kind} head format {fmt}; this version reads format {FORMAT}")
    dim = files.field(cfg, "dim", int, cfg_file, lo=0, hi=MAX_DIM)
    ks = files.field(cfg, "ks", list, cfg_file)
    if not 1 <= len(ks) <= MAX_KS or any(type(k) is not int or not 1 <= k <= MAX_K for k in ks):
        raise files.HeadFileError(cfg_file, f"'ks' is {json.dumps(ks)[:60]}, not 1 to {MAX_KS} ints in [1, {MAX_K}]")
    ks = tuple(ks)
    encoder = files.field(cfg, "encoder", (str, type(None)), cfg_file, default=None)
    known = {
        "kind",
        "format",
        "dim",
        "ks",
        "inputs",
        "feature_k",
        "hidden",
        "thresholds",
        "tops",
        "encoder",
        "name",
        "input",
        "output",
    }
    info = json.dumps({k: v for k, v in cfg.items() if k not in known})  # json-not-written: save writes it
    if kind == KIND_STATS:
        for key, want in (("thresholds", THRESHOLDS), ("tops", TOPS)):
            got = files.field(cfg, key, list, cfg_file, default=list(want))
            if got != list(want):
                raise files.HeadFileError(
                    cfg_file, f"{key} {json.dumps(got)[:60]} differ from this version's {list(want)}"
                )
        arrays = files.read_arrays(par_file, param_shapes(kind, len(ks)))
        if not np.all(arrays["sd"] > 0):
            raise files.HeadFileError(par_file, "array sd holds values <= 0 (a standard deviation)")
        files.check_magnitudes(arrays, par_file, MIN_SD)
        params = {k: jnp.asarray(arrays[k]) for k in ("mu", "sd", "w", "b")}
        return StatsHead(
            params=params,
            prior_logit=jnp.float32(arrays["prior_logit"]),
            dim=dim,
            ks=ks,
            encoder=encoder,
            info=info,
            source=str(folder),
        )
    inputs = files.field(cfg, "inputs", str, cfg_file)
    if inputs not in ("logit", "features"):
        raise files.HeadFileError(cfg_file, f"'inputs' is {inputs[:40]!r}, not 'logit' or 'features'")
    fk = files.field(cfg, "feature_k", int, cfg_file, lo=1, hi=MAX_K)
    hidden = files.field(cfg, "hidden", int, cfg_file, lo=1, hi=MAX_UNITS)
    arrays = files.read_arrays(par_file, param_shapes(kind, len(ks), hidden, inputs))
    f, att = arrays["mu"].shape[0], arrays["wa"].shape[0]
    shapes = {"sd": (f,), "w1": (f, hidden), "V": (hidden, att), "bV": (att,), "U": (hidden, att), "bU": (att,)}
    bad = next((n for n, want in shapes.items() if arrays[n].shape != want), None)
    if bad is not None or (inputs == "features" and f <= len(ks)) or att > MAX_UNITS:
        what = (
            f"array {bad} has shape {arrays[bad].shape}, expected {shapes[bad]}"
            if bad
            else f"{f} instance inputs and {att} attention units do not fit a {inputs} head of {len(ks)} logit means"
        )
        raise files.HeadFileError(par_file, f"{what} (inputs, hidden and attention units must agree)")
    if not np.all(arrays["sd"] > 0):
        raise files.HeadFileError(par_file, "array sd holds values <= 0 (a standard deviation)")
    files.check_magnitudes(arrays, par_file, MIN_SD)
    params = {k: jnp.asarray(v) for k, v in arrays.items() if k != "prior_logit"}
    return MilHead(
        params=params,
        prior_logit=jnp.float32(arrays["prior_logit"]),
        dim=dim,
        ks=ks,
        inputs=inputs,
        feature_k=fk,
        hidden=hidden,
        encoder=encoder,
        info=info,
        source=str(folder),
    )
