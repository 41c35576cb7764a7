"""Slide heads: one tumour logit for a slide from the finest-level views read so far.

Every head implements :class:`SlideHeadProtocol` (``kind``, ``score``, ``score_logits``, the per-view scores
``view_logits``, ``save`` and the class method ``load``) and is a pytree, so the functions below are pure JAX,
jittable and vmappable over slides padded to one grid. :func:`load` reads any head folder, choosing the class
by the ``kind`` in its ``config.json`` (:data:`HEADS`)::

    from histojax.reading import heads
    head = heads.load("baselines/published/c16-v2-head")
    logit = heads.score(head, grid_features, read_mask)      # (H, W, D), (H, W) bool -> () float32

Kinds: ``neighbourhood-pooled-logit`` (:class:`~histojax.reading.heads.logit.LogitHead`, a calibrated pooled
view logit), ``attention-mil`` and ``pooled-statistics`` (:class:`~histojax.reading.heads.mil.MilHead`,
:class:`~histojax.reading.heads.mil.StatsHead`, trained heads), ``learned-attention-mil``
(:class:`~histojax.reading.heads.learned.LearnedHead`, an attention-MIL learned from any encoder's features).
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol, runtime_checkable

import jax
import jax.numpy as jnp

from histojax.reading.heads import files, learned, logit, mil


@runtime_checkable
class SlideHeadProtocol(Protocol):
    """What every slide head provides. ``kind``: the string saved in ``config.json``; ``name``: a short
    description (a logit head also has ``dim``, the feature entry of its view tumour logit; a learned head has
    ``features_dim``, the length of the feature vectors it reads)."""

    kind: str

    def view_logits(self, grid_features: jax.Array) -> jax.Array:
        """The per-view scores ``(H, W)`` float32 the head reads from the feature grid ``(H, W, D)``."""

    def score(self, grid_features: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Slide tumour logit ``()`` float32 from the feature grid ``(H, W, D)`` and the read views ``(H, W)`` bool."""

    def score_logits(self, logits: jax.Array, read_mask: jax.Array) -> jax.Array:
        """Slide tumour logit ``()`` float32 from the ``(H, W)`` view-logit map and the read views ``(H, W)`` bool."""

    def save(self, folder) -> Path:
        """Write the head to ``folder`` (``config.json`` and its parameters); returns the folder."""

    @classmethod
    def load(cls, folder) -> "SlideHeadProtocol":
        """Read a head of this class's kind; ``ValueError`` naming the file, one line, on anything malformed."""


HEADS: dict[str, type] = {
    logit.KIND: logit.LogitHead,
    mil.KIND_MIL: mil.MilHead,
    mil.KIND_STATS: mil.StatsHead,
    learned.KIND: learned.LearnedHead,
}
"""kind (``config.json``'s ``"kind"``) -> head class."""


def encoder_family(name) -> str | None:
    """An encoder name as heads compare it (a head reads the features of the encoder it was fitted on): features
    imported from ``.h5`` files (``imported:FILE``: one name per slide) are one family, ``"imported"``; any other
    name (or None) is itself."""
    return "imported" if isinstance(name, str) and name.startswith("imported:") else name


def _imported_folder(name) -> bool:
    """Whether an encoder name of imported features names their folder and file layout
    (``imported:FOLDER/SUBFOLDER/*.h5``, :func:`data_tools.features.hdf5.imported_encoder`), not only the family
    (``imported``) or one slide's file (``imported:NAME.h5``, as imports before it recorded)."""
    return isinstance(name, str) and name.startswith("imported:") and name.endswith("/*.h5")


def same_encoder(a, b) -> bool:
    """Whether two recorded encoder names (a head's, a dataset's, a bundle's feature grid's) name one encoder's
    features: equal names; or, for features imported from ``.h5`` files (:func:`encoder_family` ``imported``), the
    same folder and file layout when both record it, else (either names only the family or one slide's file, which
    cannot tell two imports apart) the family alone. An unknown name (None, empty) is not a difference."""
    if not a or not b or a == b:
        return True
    if encoder_family(a) != encoder_family(b):
        return False
    return not (_imported_folder(a) and _imported_folder(b))


def encoder_mismatch(head, encoders) -> str | None:
    """What is wrong, in words, when ``head`` (its recorded ``encoder``) scores slides whose feature grids record
    ``encoders`` (names, one per slide or per kind): ``"a slide head for X features; these slides hold Y features"``,
    or ``None`` when every one is the head's (:func:`same_encoder`) or the head records none."""
    want = getattr(head, "encoder", None)
    other = sorted({str(e) for e in encoders if e and not same_encoder(want, e)})
    if not want or not other:
        return None
    return f"a slide head for {want} features; these slides hold {', '.join(other)} features"


def load(folder) -> SlideHeadProtocol:
    """Read the slide head saved in ``folder``, of the class its ``config.json``'s ``kind`` names, through the
    guarded reader (:mod:`histojax.reading.heads.files`). ``ValueError`` naming the file, one line, on anything
    missing, malformed, oversized or of an unknown kind."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a slide head folder (a folder holding config.json and its parameters)")
    cfg_file = folder / files.CONFIG
    cfg = files.read_config(cfg_file)  # a regular file of bounded size and nesting: one line, never a hang
    kind = cfg.get("kind")
    cls = HEADS.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise ValueError(f"{cfg_file}: not a slide head this version reads (kind {kind!r}; known: {', '.join(HEADS)})")
    return cls.load(folder)


def score(head: SlideHeadProtocol, grid_features: jax.Array, read_mask: jax.Array) -> jax.Array:
    """Slide tumour logit ``()`` float32 from the finest-level feature grid ``(H, W, D)`` and the read
    tissue views ``(H, W)`` bool."""
    return head.score(grid_features, read_mask)


def score_logits(head: SlideHeadProtocol, logits: jax.Array, read_mask: jax.Array) -> jax.Array:
    """Slide tumour logit ``()`` float32 from a ``(H, W)`` view-logit map and the read mask ``(H, W)`` bool
    (a head that reads all feature entries raises: give it the grid, :func:`score`)."""
    return head.score_logits(logits, read_mask)


def probability(head: SlideHeadProtocol, grid_features: jax.Array, read_mask: jax.Array) -> jax.Array:
    """``sigmoid(score(...))``: the slide's tumour probability ``()`` in [0, 1]."""
    return jax.nn.sigmoid(score(head, grid_features, read_mask))


def score_set(head: SlideHeadProtocol, views: jax.Array, mask: jax.Array) -> jax.Array:
    """Slide tumour logit ``()`` float32 from a set of views without their grid, ``views (N, D)`` read where
    ``mask (N,)`` bool: :func:`score` of a grid of one column ``(N, 1, D)``, so no view has a neighbour (a logit head
    pools the views themselves; an attention head is unchanged by the layout)."""
    return score(head, jnp.asarray(views)[:, None, :], jnp.asarray(mask, bool)[:, None])


score_sets = jax.jit(jax.vmap(score_set, in_axes=(None, 0, 0)))
"""Jitted :func:`score_set` over padded bags: ``(B, N, D)`` views, ``(B, N)`` masks (False on padding) → ``(B,)``
logits."""

score_batch = jax.jit(jax.vmap(score_logits, in_axes=(None, 0, 0)))
"""Jitted :func:`score_logits` over a batch: ``(B, H, W)`` logits, ``(B, H, W)`` masks → ``(B,)`` logits
(slides padded to one grid with masks False there)."""
