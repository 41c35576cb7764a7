"""A slide head learned from the features themselves: gated-attention MIL over the read views, no entry special.

Any encoder's features work (pcam-cnn's 64 numbers, or UNI / CONCH / Virchow vectors imported from TRIDENT or
CLAM ``.h5`` files): nothing here reads a particular entry. For each view with feature vector ``x`` (``D``
entries):

* standardise: ``x̂ = (x − μ) / σ`` (per entry, from the training views);
* instance embedding ``h = relu(W₁ x̂ + b₁)`` (``hidden`` units; ``layers=2`` adds ``h = relu(W₂ h + b₂)``);
* gated attention ``a = wₐ · (tanh(V h + b_V) ⊙ σ(U h + b_U))`` (Ilse et al. 2018; CLAM's and SASHA's heads);
* slide embedding ``z = Σ softmax(a) h`` over the **read** views only, slide logit ``s = w_c · z + b_c``;
* calibration (Platt, fitted on validation slides): reported logit ``c·s + d`` (``cal_a``, ``cal_b``).

A slide with nothing read scores ``prior_logit`` (the training split's log odds of tumour). The **per-view
score** is the instance logit through the same calibration, ``c·(w_c · h + b_c) + d``: what maps, scripted
readers and coarse maps use (:meth:`LearnedHead.view_logits`, on any level's grid of the same encoder).

**Incremental scoring.** Attention pooling is a softmax-weighted mean, so a slide's state is three running
sums: ``m`` (the largest attention read so far), ``S = Σ exp(a − m)`` and ``Z = Σ exp(a − m) h``
(:class:`PoolState`). Reading new views adds their terms, rescaling the old ones by ``exp(m_old − m_new)``
when the maximum moves (:meth:`LearnedHead.add`): O(views newly read), never a rescoring of the slide; the
logit is ``c·(w_c · Z / S + b_c) + d`` (:meth:`LearnedHead.logit`). :meth:`LearnedHead.score` is the same
sums over every read view at once, so the two agree to float rounding. A view must be added once (the caller
adds newly read views only).

Pure JAX, jittable, vmappable over slides padded to one grid (padding is never read)::

    head = LearnedHead.load("runs/learned-head")   # saved by baselines.reading.learned_head_fit
    logit = head.score(grid_features, read_mask)          # (H, W, D), (H, W) bool -> () float32
    scores = head.view_logits(grid_features)              # (H, W) float32 per-view scores
    st = head.init_state()
    st = head.add_views(st, new_features, new_mask)       # (K, D), (K,) bool
    logit = head.logit(st)

**Faster still: cached view terms.** The slide logit is linear in ``z``, so it is the softmax(a)-weighted mean
of the views' raw instance logits ``u = w_c · h + b_c``. :meth:`LearnedHead.view_terms` computes ``(a, u)`` once
per slide (``(H, W, 2)``); then :meth:`LearnedHead.score_terms` scores any read mask and
:meth:`LearnedHead.add_terms` / :meth:`LearnedHead.logit_terms` update a three-number state, in O(views) with no
feature vector read again: what an env's head reward should hold per slide.

Fitted by :mod:`baselines.reading.learned_head_fit`. Saved as a folder (:mod:`histojax.reading.heads.files`):
``config.json`` (``kind`` :data:`KIND`, ``format`` :data:`FORMAT`, ``features_dim``, ``hidden``, ``attention``, ``layers``,
the fit) and ``params.npz`` (the arrays, ``cal_a``, ``cal_b``, ``prior_logit``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from histojax.reading.heads import files

KIND = "learned-attention-mil"
FORMAT = 1
NEG = -1e30  # the running maximum of a slide with nothing read (finite: exp(NEG - NEG) is 1, not nan)
MAX_DIM = 1 << 16
MAX_UNITS = 4096
MAX_PARAM = files.MAX_ARRAY_VALUE
"""The largest magnitude of any array entry read (weights, biases, ``mu``, ``cal_a``, ``cal_b``, ``prior_logit``),
as the logit heads bound theirs: a fitted head's are a few units (weight decay; a calibration of a few units)."""
MIN_SD = 1e-4
"""The smallest standardisation ``sd`` read: the fit adds 1e-3 to every feature's standard deviation, so a
smaller one is not a fitted head's (``x / 1e-40`` overflows float32)."""


class PoolState(NamedTuple):
    """A slide's attention-pooling state (a pytree; batch it by stacking): ``m ()`` the largest attention read
    (``NEG`` when nothing is), ``s ()`` = Σ exp(a − m), ``z (hidden,)`` = Σ exp(a − m)·h over the views read."""

    m: jax.Array
    s: jax.Array
    z: jax.Array


def param_shapes(dim: int, hidden: int, attention: int, layers: int) -> dict:
    """Name -> shape of every array of a head with ``dim`` feature entries, ``hidden`` units, ``attention``
    attention units and ``layers`` (1 or 2) instance layers (``cal_a``, ``cal_b``, ``prior_logit`` included)."""
    shapes = {"mu": (dim,), "sd": (dim,), "w1": (dim, hidden), "b1": (hidden,)}
    if layers == 2:
        shapes.update(w2=(hidden, hidden), b2=(hidden,))
    shapes.update(
        V=(hidden, attention),
        bV=(attention,),
        U=(hidden, attention),
        bU=(attention,),
        wa=(attention,),
        wc=(hidden,),
        bc=(),
        cal_a=(),
        cal_b=(),
        prior_logit=(),
    )
    return shapes


SCALARS = ("cal_a", "cal_b", "prior_logit")


@struct.dataclass
class LearnedHead(files.SavedHead):
    """A gated-attention MIL head over any encoder's features (see the module doc). Leaves: ``params`` (dict of
    arrays: ``mu``, ``sd`` ``(D,)``; ``w1 (D, H)``, ``b1``; optional ``w2 (H, H)``, ``b2``; ``V``, ``U``
    ``(H, A)``, ``bV``, ``bU``, ``wa (A,)``; ``wc (H,)``, ``bc ()``), ``cal_a`` / ``cal_b`` (calibration: logit =
    ``cal_a · s + cal_b``), ``prior_logit`` (nothing read). Static: ``features_dim`` (D; not ``dim``, which the logit
    heads use for the entry they read: this head reads none on its own), ``hidden`` (H), ``attention``
    (A), ``layers`` (1 or 2), ``encoder`` (the features' encoder, as recorded in the bundles), ``info`` (JSON text
    of the fit, merged into config.json), ``source`` (the folder it was loaded from; None for a head in memory)."""

    params: dict
    cal_a: jax.Array = 1.0
    cal_b: jax.Array = 0.0
    prior_logit: jax.Array = 0.0
    features_dim: int = struct.field(pytree_node=False, default=64)
    hidden: int = struct.field(pytree_node=False, default=64)
    attention: int = struct.field(pytree_node=False, default=32)
    layers: int = struct.field(pytree_node=False, default=1)
    encoder: str | None = struct.field(pytree_node=False, default=None)
    info: str = struct.field(pytree_node=False, default="{}")
    source: str | None = struct.field(pytree_node=False, default=None)
    kind = KIND

    @property
    def name(self) -> str:
        """A short name, e.g. ``"learned attention-MIL, 64-d features, 1 x 64 units"``."""
        return f"learned attention-MIL, {self.features_dim}-d features, {self.layers} x {self.hidden} units"

    # ------------------------------------------------------------------ per view
    def embed(self, x: jax.Array) -> jax.Array:
        """Instance embeddings ``(..., hidden)`` of feature vectors ``x (..., D)``."""
        p = self.params
        x = (jnp.asarray(x, jnp.float32) - p["mu"]) / p["sd"]
        h = jax.nn.relu(x @ p["w1"] + p["b1"])
        if self.layers == 2:
            h = jax.nn.relu(h @ p["w2"] + p["b2"])
        return h

    def attention_logits(self, h: jax.Array) -> jax.Array:
        """Gated attention ``(...)`` of instance embeddings ``h (..., hidden)``."""
        p = self.params
        gate = jnp.tanh(h @ p["V"] + p["bV"]) * jax.nn.sigmoid(h @ p["U"] + p["bU"])
        return gate @ p["wa"]

    def raw_logit(self, z: jax.Array) -> jax.Array:
        """Uncalibrated logit ``w_c · z + b_c`` ``(...)`` of embeddings ``z (..., hidden)``."""
        return z @ self.params["wc"] + self.params["bc"]

    def calibrate(self, s: jax.Array) -> jax.Array:
        """``cal_a · s + cal_b``: the calibrated logit of raw logits ``s``."""
        return self.cal_a * s + self.cal_b

    def view_logits(self, grid_features: jax.Array) -> jax.Array:
        """Per-view scores ``(H, W)`` float32 (the calibrated instance logit of each view) of a feature grid
        ``(H, W, D)`` (any level of the same encoder: the finest for maps, a coarse one for a coarse map)."""
        return self.calibrate(self.raw_logit(self.embed(grid_features))).astype(jnp.float32)

    view_scores = view_logits

    # ------------------------------------------------------------------ incremental pooling
    def init_state(self) -> PoolState:
        """The state of a slide with nothing read."""
        return PoolState(jnp.float32(NEG), jnp.float32(0.0), jnp.zeros(self.hidden, jnp.float32))

    def add(self, state: PoolState, h_new: jax.Array, a_new: jax.Array, mask_new: jax.Array) -> PoolState:
        """``state`` with the views ``h_new (K, hidden)`` / attention ``a_new (K,)`` added where ``mask_new (K,)``
        bool (views not yet in the state: adding a view twice counts it twice). O(K)."""
        mask = jnp.asarray(mask_new, bool)
        a = jnp.where(mask, a_new, NEG)
        m = jax.lax.stop_gradient(jnp.maximum(state.m, jnp.max(a, initial=NEG)))  # softmax is invariant to m
        scale = jnp.exp(state.m - m)
        e = jnp.where(mask, jnp.exp(jnp.where(mask, a_new - m, 0.0)), 0.0)
        return PoolState(m, state.s * scale + e.sum(), state.z * scale + e @ h_new)

    def add_views(self, state: PoolState, x_new: jax.Array, mask_new: jax.Array) -> PoolState:
        """:meth:`add` of the feature vectors ``x_new (K, D)`` read where ``mask_new (K,)`` bool."""
        h = self.embed(x_new)
        return self.add(state, h, self.attention_logits(h), mask_new)

    def logit(self, state: PoolState) -> jax.Array:
        """The calibrated slide logit ``()`` float32 of ``state`` (``prior_logit`` when nothing is read)."""
        z = state.z / jnp.maximum(state.s, 1e-30)
        return jnp.where(state.s > 0, self.calibrate(self.raw_logit(z)), self.prior_logit).astype(jnp.float32)

    # ------------------------------------------------------------------ cached view terms (the fast path)
    def view_terms(self, features: jax.Array) -> jax.Array:
        """``(..., 2)`` float32: each view's attention ``a`` and raw instance logit ``u = w_c · h + b_c`` of
        feature vectors ``(..., D)``. The slide logit is linear in the pooled ``z``, so it is the softmax(a)-weighted
        mean of ``u``: compute these once per slide and every later score (any read mask) costs O(views), with no
        feature read again (:meth:`score_terms`, :meth:`add_terms`)."""
        h = self.embed(features)
        return jnp.stack([self.attention_logits(h), self.raw_logit(h)], -1).astype(jnp.float32)

    def init_terms_state(self) -> PoolState:
        """The state of :meth:`add_terms` for a slide with nothing read (``z`` holds Σ exp(a − m)·u, shape ``(1,)``)."""
        return PoolState(jnp.float32(NEG), jnp.float32(0.0), jnp.zeros(1, jnp.float32))

    def add_terms(self, state: PoolState, terms_new: jax.Array, mask_new: jax.Array) -> PoolState:
        """:meth:`add` on cached :meth:`view_terms` ``(K, 2)`` of views newly read where ``mask_new (K,)``: O(K)."""
        t = jnp.asarray(terms_new, jnp.float32)
        return self.add(state, t[:, 1:], t[:, 0], mask_new)

    def logit_terms(self, state: PoolState) -> jax.Array:
        """The calibrated slide logit ``()`` of a :meth:`add_terms` state (``prior_logit`` when nothing is read)."""
        u = state.z[0] / jnp.maximum(state.s, 1e-30)
        return jnp.where(state.s > 0, self.calibrate(u), self.prior_logit).astype(jnp.float32)

    def score_terms(self, terms: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Slide logit ``()`` from cached :meth:`view_terms` ``(H, W, 2)`` (or ``(N, 2)``) read where ``read_mask``;
        equals :meth:`score` of the features they came from."""
        t = jnp.asarray(terms, jnp.float32).reshape(-1, 2)
        state = self.add_terms(self.init_terms_state(), t, jnp.asarray(read_mask, bool).reshape(-1))
        return self.logit_terms(state)

    # ------------------------------------------------------------------ whole slides
    def score_views(self, features: jax.Array, mask: jax.Array) -> jax.Array:
        """Slide logit ``()`` float32 from a set of views ``features (N, D)`` read where ``mask (N,)`` bool."""
        return self.logit(self.add_views(self.init_state(), features, mask))

    def score(self, grid_features: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Slide tumour logit ``()`` float32 from the finest-level feature grid ``(H, W, D)`` and the read tissue
        views ``(H, W)`` bool."""
        g = jnp.asarray(grid_features)
        return self.score_views(g.reshape(-1, g.shape[-1]), jnp.asarray(read_mask, bool).reshape(-1))

    def score_logits(self, logits: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Not available: this head reads every feature entry, not a view-logit map (call :meth:`score`)."""
        raise ValueError(
            f"this head ({self.name}) reads all feature entries: call score with the feature grid "
            "(H, W, D), not score_logits with a logit map"
        )

    # ------------------------------------------------------------------ files
    FORMAT = FORMAT
    OUTPUT = "slide tumour logit (sigmoid: probability); per-view scores: calibrated instance logits"

    def structure(self) -> dict:
        """The structure entries of ``config.json`` (:meth:`files.SavedHead.config`)."""
        return {
            "features_dim": int(self.features_dim),
            "hidden": int(self.hidden),
            "attention": int(self.attention),
            "layers": int(self.layers),
        }

    def arrays(self) -> dict:
        """Every array saved in ``params.npz`` (name -> float32 numpy array)."""
        out = {k: np.asarray(v, np.float32) for k, v in self.params.items()}
        for k in SCALARS:
            out[k] = np.asarray(getattr(self, k), np.float32)
        return out

    def save(self, folder, extras: dict | None = None) -> Path:
        """Write ``folder/config.json`` and ``folder/params.npz`` atomically (plus ``extras``: file name -> bytes),
        refusing a folder that holds anything else (:func:`histojax.reading.heads.files.save_folder`)."""
        return files.save_folder(folder, self.config(), self.arrays(), extras)

    @classmethod
    def load(cls, folder) -> "LearnedHead":
        """Read a head saved by :meth:`save` through the guarded reader (:mod:`histojax.reading.heads.files`).
        ``ValueError`` naming the file, one line, on anything missing, malformed or of another kind / format."""
        folder = Path(folder)
        cfg_file = folder / files.CONFIG
        cfg = files.read_config(cfg_file)
        kind = cfg.get("kind")
        if kind != KIND:
            raise files.HeadFileError(cfg_file, f"a head of kind {kind!r}, not {KIND!r}")
        fmt = files.field(cfg, "format", int, cfg_file)
        if fmt != FORMAT:
            raise files.HeadFileError(cfg_file, f"{KIND} head format {fmt}; this version reads format {FORMAT}")
        dim = files.field(cfg, "features_dim", int, cfg_file, lo=1, hi=MAX_DIM)
        hidden = files.field(cfg, "hidden", int, cfg_file, lo=1, hi=MAX_UNITS)
        att = files.field(cfg, "attention", int, cfg_file, lo=1, hi=MAX_UNITS)
        layers = files.field(cfg, "layers", int, cfg_file, lo=1, hi=2)
        encoder = files.field(cfg, "encoder", (str, type(None)), cfg_file, default=None)
        arrays = files.read_arrays(folder / files.PARAMS, param_shapes(dim, hidden, att, layers))
        files.check_magnitudes(arrays, folder / files.PARAMS, MIN_SD)  # finite but absurd: refused as well
        known = {
            "kind",
            "format",
            "features_dim",
            "hidden",
            "attention",
            "layers",
            "encoder",
            "name",
            "input",
            "output",
            "files",
        }
        info = json.dumps({k: v for k, v in cfg.items() if k not in known})  # json-not-written: files.save writes it
        params = {k: jnp.asarray(v) for k, v in arrays.items() if k not in SCALARS}
        return cls(
            params=params,
            cal_a=jnp.float32(arrays["cal_a"]),
            cal_b=jnp.float32(arrays["cal_b"]),
            prior_logit=jnp.float32(arrays["prior_logit"]),
            features_dim=dim,
            hidden=hidden,
            attention=att,
            layers=layers,
            encoder=encoder,
            info=info,
            source=str(folder),
        )


def init_params(
    key: jax.Array, dim: int, hidden: int = 64, attention: int = 32, layers: int = 1, mu=None, sd=None
) -> dict:
    """Initial parameters (Glorot-uniform weights, zero biases) of a head with ``dim`` feature entries;
    ``mu`` / ``sd`` ``(dim,)`` the standardisation (default 0 / 1)."""
    ks = jax.random.split(key, 6)
    g = jax.nn.initializers.glorot_uniform()
    p = {
        "mu": jnp.zeros(dim) if mu is None else jnp.asarray(mu, jnp.float32),
        "sd": jnp.ones(dim) if sd is None else jnp.asarray(sd, jnp.float32),
        "w1": g(ks[0], (dim, hidden)),
        "b1": jnp.zeros(hidden),
    }
    if layers == 2:
        p.update(w2=g(ks[5], (hidden, hidden)), b2=jnp.zeros(hidden))
    p.update(
        V=g(ks[1], (hidden, attention)),
        bV=jnp.zeros(attention),
        U=g(ks[2], (hidden, attention)),
        bU=jnp.zeros(attention),
        wa=g(ks[3], (attention, 1))[:, 0],
        wc=g(ks[4], (hidden, 1))[:, 0],
        bc=jnp.zeros(()),
    )
    return p


def load(folder) -> LearnedHead:
    """:meth:`LearnedHead.load`."""
    return LearnedHead.load(folder)


def score(head: LearnedHead, grid_features: jax.Array, read_mask: jax.Array) -> jax.Array:
    """:meth:`LearnedHead.score`: slide logit ``()`` of a ``(H, W, D)`` grid read where ``(H, W)`` bool."""
    return head.score(grid_features, read_mask)


score_batch = jax.jit(jax.vmap(score, in_axes=(None, 0, 0)))
"""Jitted :func:`score` over slides padded to one grid: ``(B, H, W, D)``, ``(B, H, W)`` → ``(B,)`` logits."""
