"""Fit a slide head learned from any encoder's features (:class:`histojax.reading.heads.learned.LearnedHead`):
``python -m baselines.reading.learned_head_fit --dataset DIR --out DIR [--seed S] [--val-fraction F]``.

**Data.** The finest level's feature vector of every tissue view (the views the readers count:
:func:`histojax.core.seen_views.tissue_views`) of each training slide, read through the bundle's checked
loader (:func:`data_tools.bundle_files.reading.load_feature_levels`: metadata digest and array checksums verified).
No feature entry is special: any encoder, any ``D``. The validation share is
:func:`baselines.validation.split_train` (``--val-fraction`` 0.2, ``--split-seed`` 0, as the other head fits);
the test split is never read while fitting.

**Training** (:func:`train`): Adam with decoupled weight decay (optax ``adamw``), a jitted step over
``--batch`` slides drawn at random (classes balanced). Each slide of a step is read at random, as a reader
reads: all its tissue with probability 0.25, else cells of 4 × 4 views each read with a probability drawn
log-uniformly in [2 %, 100 %]; at most ``--views`` of the views read are kept, so a step costs the same on any
slide size: ``--top-share`` of them (default half) the views of highest attention under the model being
trained (refreshed every ``--eval-every`` steps: a small tumour's views dominate the pooling of the whole read,
and a uniform draw of 512 of 10,000 views would mostly miss them), the rest drawn uniformly. Loss: the slide-level
log loss plus ``--instance-weight`` (default 0.5) × an instance loss on the instance logits (the per-view
scores; MI-Net / CLAM style): every view of a normal slide is normal, and the highest view of a tumour slide read
whole is tumour.

**Choice on validation only** (:data:`CANDIDATES`, ``--hidden``): each candidate structure is trained for
``--steps`` steps; its validation AUC reading everything and its validation log loss are measured every
``--eval-every`` steps, and the checkpoint kept over candidates and steps is the one of highest validation AUC
**smoothed** over neighbouring checks (:func:`smooth_curve`; ties: the lower validation loss, then the AUC reading
random 10 %): on a few validation slides one lucky check no longer wins. **Calibration**: a Platt
scaling ``c·s + d`` fitted on the validation slides' logits (reading everything and reading random 10 %,
pooled). The prior (nothing read) is the training split's log odds of tumour.

**Guards** (one line naming the dataset, exit 2, nothing saved): a validation share with fewer than
:data:`baselines.validation.MIN_VALIDATION_PER_CLASS` slides of a class (before anything is read or trained);
fewer than :data:`MIN_SLIDES_PER_CLASS` training slides of either class after the validation share is held out;
a validation split with one class;
a chosen head whose validation AUC is below 0.5 (inverted) or whose calibration slope is negative.

Saved to ``--out`` (:meth:`LearnedHead.save`, atomic; never over a folder of other files): ``config.json``
(structure, the fit, every candidate's validation figures, and what it was fitted on:
:data:`baselines.reading.provenance.RECORD`, the dataset's seal, split, fold and the fitting and validation slides),
``params.npz`` and ``learning_curve.png``. ``--all-folds`` (a dataset built with ``--folds K``): one head per fold,
``OUT/fold0`` … ``OUT/fold{K-1}``, each fitted on the other folds (as ``--fold I --out OUT/foldI``).

**A rerun keeps finished heads** (:func:`baselines.reading.fitting.claim_head`, before any slide is read): ``--out``
holding a finished head of this command (``config.json``'s ``fit_options``) fits nothing, in one line; with
``--all-folds`` each fold's finished head is kept (``fold I: finished, kept``) and only the missing folds are fitted,
so a kill during fold 2 loses only fold 2's fit (a fit's progress within one fit is not kept). A head of other
options is refused naming the first difference (every fold checked before any is fitted); ``--restart`` moves the
head (with ``--all-folds``: the whole ``OUT``) aside to ``OUT.previous-N``, never deleted, and fits again.

``--score HEAD --split test`` scores a saved head on a split reading everything: AUC over all slides and
without ITC-only slides (lesion classes as :mod:`baselines.reading.readers` defines them). A split holding slides
the head was fitted or validated on is refused (``--allow-fitting-slides``: scored, with a warning). ``--rotate SEED``
multiplies every feature vector by a fixed random orthogonal matrix (drawn from ``SEED``) before fitting or
scoring: a check that nothing depends on which entry holds what.
"""

from __future__ import annotations

import datetime
import io
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax

from baselines.published_agents import published_or_path
from baselines.reading.fitting import (  # the same minimum as the logit and MIL fits
    CHANCE_FLAG,
    MIN_SLIDES_PER_CLASS,
    OPTIONS,
    add_restart,
    chance_warning,
    claim_head,
    fit_options,
    head_state,
    move_head_aside,
    refusal,
)
from baselines.reading.provenance import (
    RECORD,
    add_flag,
    check_scored,
    fit_record,
    head_config,
    head_for_fold,
    record_of,
    seen_slides,
)
from baselines.reading.slides import HeadDataError, finest_views, lesion_of, read_bundle, warn_scale
from baselines.reading.slides import read_spec as read_sealed_spec
from baselines.validation import check_all_folds, check_validation_share, split_train
from data_tools.annotations import load_annotations
from data_tools.bundle_files.safe_files import own_file
from data_tools.cli_output import command_main, print_error, progress_bar
from data_tools.errors import HistojaxDataError
from data_tools.metrics import (
    UNDEFINED,
    auc_interval,
    format_auc,
    json_safe,
    roc_auc,
    roc_auc_with_interval,
    small_split_warning,
)
from histojax.loading import slide_label_from_metadata
from histojax.reading.heads import encoder_mismatch, files
from histojax.reading.heads.learned import KIND, LearnedHead, init_params

CELL = 4  # random reads pick cells of CELL × CELL views (a reader's cell is about 4 × 4 views)
P_FULL = 0.25  # share of training reads that read all tissue
MIN_READ = 0.02  # smallest random read fraction
CANDIDATES = ({"hidden": 32, "attention": 16, "layers": 1}, {"hidden": 64, "attention": 32, "layers": 1})
"""The structures tried (``--hidden`` picks among them by hidden size)."""


class FitError(HistojaxDataError):
    """A dataset this fit refuses (file named, one line)."""


# ----------------------------------------------------------------------------- data
def read_spec(dataset, fold: int | None = None) -> dict:
    """``dataset.json`` of ``dataset`` (``FitError`` naming it when missing, malformed or without a train list).
    ``fold=i`` (a dataset built with ``--folds K``): its train / validation / test lists are fold i's sides
    (:func:`histojax.datasets.with_fold`; no folds or a fold out of range: ``FitError`` naming the file)."""
    try:
        return read_sealed_spec(dataset, fold)  # its seal checked: an edited label or split is refused
    except HeadDataError as e:
        raise FitError(e.path, e.problem) from None


def slide_label(spec: dict, name: str, metadata) -> int:
    """A slide's label as the env reads it: ``dataset.json``'s ``labels`` when it names the slide, else the
    bundle's own (tumour annotated or not)."""
    labels = spec.get("labels")
    if isinstance(labels, dict):
        for key, value in labels.items():
            if Path(key).name == name:
                return int(value)
    return int(slide_label_from_metadata(metadata))


def load_views(bundle, label: int | None = None, spec: dict | None = None, verify: bool = True) -> dict:
    """One bundle's tissue views through the checked loader: ``features (N, D)`` float16 (the finest feature
    grid's cell under each tissue view), ``yx (N, 2)`` int32 view rows / columns, ``shape (gh, gw)`` of the
    finest view grid, ``label``, ``name``, ``encoder``, ``mpp``, ``tile``, ``bundle``. ``FitError`` naming the
    bundle on anything missing or corrupt."""
    bundle = Path(bundle)
    try:
        meta, grids, stride, tissue_mask = read_bundle(bundle, (0,), verify)  # the head tools' one checked read
        fg = grids[0]
        tissue, fy, fx, tile = finest_views(meta, fg.shape, stride, tissue_mask)
        gh, gw = tissue.shape
        ys, xs = np.nonzero(tissue)
        features = np.asarray(fg[fy[ys], fx[xs]], np.float16)
        lab = slide_label(spec or {}, bundle.name, meta) if label is None else int(label)
    except HistojaxDataError:
        raise
    except (OSError, KeyError, IndexError, TypeError, ValueError) as e:
        raise FitError(bundle, f"unreadable bundle ({type(e).__name__}: {' '.join(str(e).split())[:120]})") from None
    if ys.size == 0:
        raise FitError(bundle, "has no tissue views at the finest level")
    if not np.all(np.isfinite(features)):
        raise FitError(bundle, "non-finite feature values on tissue views (or beyond float16's range)")
    mpp = (meta.get("source") or {}).get("mpp")
    return {
        "name": bundle.name,
        "label": lab,
        "features": features,
        "yx": np.stack([ys, xs], 1).astype(np.int32),
        "shape": (int(gh), int(gw)),
        "encoder": (meta.get("features") or {}).get("encoder"),
        "mpp": float(mpp) if isinstance(mpp, (int, float)) else float("nan"),
        "tile": tile,
        "bundle": bundle,
    }


def load_split(dataset, entries, spec: dict, progress: bool = True, desc: str = "loading") -> list[dict]:
    """:func:`load_views` of every entry of ``entries`` (paths relative to ``dataset`` or absolute)."""
    out = []
    for rel in progress_bar(entries, desc=desc, disable=not progress, file=sys.stderr, leave=False):
        bundle = Path(rel) if Path(rel).is_absolute() else Path(dataset) / rel
        out.append(load_views(bundle, spec=spec))
    return out


def rotation(seed: int, dim: int) -> np.ndarray:
    """A fixed random orthogonal ``(dim, dim)`` float32 matrix (QR of a Gaussian, signs fixed) drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    q, r = np.linalg.qr(rng.normal(size=(dim, dim)))
    return (q * np.sign(np.diag(r))).astype(np.float32)


def rotate(slides: list[dict], q: np.ndarray | None) -> list[dict]:
    """``slides`` with every feature vector multiplied by ``q`` (None: unchanged)."""
    if q is None:
        return slides
    return [{**s, "features": (np.asarray(s["features"], np.float32) @ q).astype(np.float32)} for s in slides]


# ----------------------------------------------------------------------------- random reads
def cells_of(s: dict) -> np.ndarray:
    """``(N,)`` the ``CELL × CELL`` cell of each tissue view of slide ``s`` (cached in ``s``)."""
    if "cell" not in s:
        cw = -(-s["shape"][1] // CELL)
        s["cell"] = (s["yx"][:, 0] // CELL) * cw + s["yx"][:, 1] // CELL
        s["n_cells"] = int((-(-s["shape"][0] // CELL)) * cw)
    return s["cell"]


def random_read(rng, s: dict, fraction: float | None) -> np.ndarray:
    """``(N,)`` bool: slide ``s``'s tissue views read when each ``CELL × CELL`` cell is read with probability
    ``fraction`` (None: all), at least one cell with tissue."""
    if fraction is None or fraction >= 1:
        return np.ones(len(s["features"]), bool)
    cell = cells_of(s)
    read = rng.random(s["n_cells"]) < fraction
    mask = read[cell]
    if not mask.any():
        mask = cell == cell[rng.integers(len(cell))]
    return mask


def draw_fraction(rng) -> float | None:
    """A training read's fraction: None (everything) with probability ``P_FULL``, else log-uniform in [2 %, 1]."""
    return None if rng.random() < P_FULL else float(np.exp(rng.uniform(np.log(MIN_READ), 0.0)))


def batch(
    rng, slides: list[dict], size: int, views: int, attention: list | None = None, top_share: float = 0.5
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(x (size, views, D) float32, mask (size, views) bool, y (size,) float32, full (size,) bool)``: ``size``
    slides drawn with
    classes balanced, each read at random (:func:`draw_fraction`). Of a read larger than ``views`` views, the
    ``top_share`` with the highest ``attention`` (per slide ``(N,)``, the model's own, refreshed while training;
    None: none) are kept and the rest drawn uniformly: the views that dominate the attention pooling of the whole
    read are the ones a small tumour lives in, and a uniform draw of 512 of 10,000 views would mostly miss them."""
    pos = [i for i, s in enumerate(slides) if s["label"]]
    neg = [i for i, s in enumerate(slides) if not s["label"]]
    d = slides[0]["features"].shape[1]
    x = np.zeros((size, views, d), np.float32)
    m = np.zeros((size, views), bool)
    y = np.zeros(size, np.float32)
    full = np.zeros(size, bool)
    for b in range(size):
        i = int(rng.choice(pos if b % 2 == 0 else neg))
        s = slides[i]
        fraction = draw_fraction(rng)
        full[b] = fraction is None
        idx = np.flatnonzero(random_read(rng, s, fraction))
        if idx.size > views:
            n_top = int(views * top_share) if attention is not None else 0
            if n_top:
                part = np.argpartition(-attention[i][idx], n_top)
                top, rest = idx[part[:n_top]], idx[part[n_top:]]
                idx = np.concatenate([top, rng.choice(rest, views - n_top, replace=False)])
            else:
                idx = rng.choice(idx, views, replace=False)
        x[b, : idx.size] = s["features"][idx]
        m[b, : idx.size] = True
        y[b] = s["label"]
    return x, m, y, full


def attention_of(head, slides: list[dict], chunk: int = 1 << 16, flat: np.ndarray | None = None) -> list[np.ndarray]:
    """Each slide's attention logits ``(N,)`` float32 under ``head``: every slide's views in one flat array
    (``flat``, the slides' features concatenated, when the caller keeps one), in chunks of ``chunk`` rows (one
    compiled shape; only the last chunk is padded)."""
    fn = jax.jit(lambda hd, x: hd.attention_logits(hd.embed(x)))
    sizes = [len(s["features"]) for s in slides]
    if flat is None:
        flat = np.concatenate([np.asarray(s["features"]) for s in slides])
    out = np.empty(len(flat), np.float32)
    for i in range(0, len(flat), chunk):
        part = flat[i : i + chunk]
        if len(part) < chunk:
            part = np.concatenate([part, np.zeros((chunk - len(part), flat.shape[1]), part.dtype)])
        out[i : i + chunk] = np.asarray(fn(head, part))[: min(chunk, len(flat) - i)]
    return np.split(out, np.cumsum(sizes)[:-1])


# ----------------------------------------------------------------------------- scoring many slides
class FlatSet:
    """The tissue views of ``slides`` concatenated (``x (N, D)`` float32, ``seg (N,)`` slide of each view), scored
    by one jitted segment pooling per head structure (:meth:`logits`), reading all views or a random share."""

    def __init__(self, slides: list[dict]):
        self.slides = slides
        self.x = np.concatenate([np.asarray(s["features"], np.float32) for s in slides])
        self.seg = np.concatenate([np.full(len(s["features"]), i, np.int32) for i, s in enumerate(slides)])
        self.labels = np.asarray([s["label"] for s in slides])
        self._fns = {}

    def _fn(self, head):

        key = (head.features_dim, head.hidden, head.attention, head.layers)
        if key not in self._fns:
            n = len(self.slides)

            def pooled(head, x, seg, mask):
                h = head.embed(x)
                a = jnp.where(mask, head.attention_logits(h), -jnp.inf)
                amax = jax.ops.segment_max(a, seg, n)
                amax = jnp.where(jnp.isfinite(amax), amax, 0.0)
                e = jnp.where(mask, jnp.exp(jnp.where(mask, a - amax[seg], 0.0)), 0.0)
                den = jax.ops.segment_sum(e, seg, n)
                z = jax.ops.segment_sum(e[:, None] * h, seg, n) / jnp.maximum(den, 1e-30)[:, None]
                return jnp.where(den > 0, head.calibrate(head.raw_logit(z)), head.prior_logit)

            self._fns[key] = jax.jit(pooled)
        return self._fns[key]

    def masks(self, rng, fraction: float | None) -> np.ndarray:
        """``(N,)`` bool: every slide read at ``fraction`` (:func:`random_read`; None = everything)."""
        return np.concatenate([random_read(rng, s, fraction) for s in self.slides])

    def logits(self, head, mask: np.ndarray | None = None) -> np.ndarray:
        """``(B,)`` slide logits of ``head`` reading ``mask`` (default every tissue view)."""
        mask = np.ones(len(self.x), bool) if mask is None else mask
        return files.check_finite_logits(
            head, self._fn(head)(head, self.x, self.seg, mask)
        )  # one line naming params.npz

    def log_loss(self, head) -> float:
        """Mean log loss (nats) of ``head``'s slide logits reading everything against the slides' labels."""
        z = self.logits(head).astype(np.float64)
        return float(np.mean(np.logaddexp(0.0, np.where(self.labels > 0, -z, z))))

    def aucs(self, head, fractions=(0.1,), draws: int = 3, seed: int = 123) -> dict:
        """``{"full": AUC reading everything, "read 0.1": mean AUC over ``draws`` random reads, ...}``."""
        out = {"full": roc_auc(self.logits(head), self.labels)}
        rng = np.random.default_rng(seed)
        for f in fractions:
            out[f"read {f:g}"] = float(
                np.mean([roc_auc(self.logits(head, self.masks(rng, f)), self.labels) for _ in range(draws)])
            )
        return out


def platt(scores: np.ndarray, labels: np.ndarray, l2: float = 1e-3, iters: int = 100) -> tuple[float, float]:
    """``(a, b)`` of the logistic regression ``P(y) = σ(a·s + b)`` (Newton, a small L2 penalty on ``a`` so a
    separable set stays finite)."""
    s = np.asarray(scores, np.float64)
    y = np.asarray(labels, np.float64)
    sc = max(float(s.std()), 1e-6)
    z = s / sc
    w = np.zeros(2)
    for _ in range(iters):
        p = 1 / (1 + np.exp(-np.clip(w[0] * z + w[1], -60, 60)))
        g = np.array([np.sum((p - y) * z) + l2 * len(y) * w[0], np.sum(p - y)])
        r = p * (1 - p)
        hm = np.array([[np.sum(r * z * z) + l2 * len(y), np.sum(r * z)], [np.sum(r * z), np.sum(r) + 1e-9]])
        step = np.linalg.solve(hm, g)
        w -= step
        if np.abs(step).max() < 1e-10:
            break
    return float(w[0] / sc), float(w[1])


# ----------------------------------------------------------------------------- training
def standardisation(slides: list[dict], limit: int = 200_000, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``(mu, sd)`` ``(D,)`` of the training slides' tissue views (at most ``limit`` of them, drawn at random)."""
    x = np.concatenate([np.asarray(s["features"], np.float32) for s in slides])
    if len(x) > limit:
        x = x[np.random.default_rng(seed).choice(len(x), limit, replace=False)]
    return x.mean(0), x.std(0) + 1e-3


def train(
    train_slides: list[dict],
    val: FlatSet | None,
    structure: dict,
    seed: int = 0,
    steps: int = 600,
    batch_size: int = 16,
    views: int = 512,
    lr: float = 2e-3,
    weight_decay: float = 1e-4,
    eval_every: int = 50,
    top_share: float = 0.5,
    instance_weight: float = 0.5,
    progress: bool = True,
) -> tuple:
    """Train a :class:`LearnedHead` of ``structure`` (``hidden``, ``attention``, ``layers``) on ``train_slides``
    (see the module doc); every ``eval_every`` steps score it on ``val`` (a :class:`FlatSet`) and refresh the
    training views' attention that :func:`batch` keeps its ``top_share`` of views by. Returns
    ``(best_head, curve)``: the checkpoint with the best validation AUC reading everything (ties: reading 10 %;
    the last one when ``val`` is None) and ``curve`` (rows of step, training loss, validation AUCs)."""
    d = int(train_slides[0]["features"].shape[1])
    mu, sd = standardisation(train_slides, seed=seed)
    p = float(np.clip(np.mean([s["label"] for s in train_slides]), 1e-3, 1 - 1e-3))
    params = init_params(
        jax.random.PRNGKey(seed), d, structure["hidden"], structure["attention"], structure["layers"], mu, sd
    )
    head0 = LearnedHead(
        params=params,
        prior_logit=jnp.float32(np.log(p / (1 - p))),
        features_dim=d,
        hidden=structure["hidden"],
        attention=structure["attention"],
        layers=structure["layers"],
        encoder=train_slides[0].get("encoder"),
    )
    frozen = {"mu": params["mu"], "sd": params["sd"]}
    tp = {k: v for k, v in params.items() if k not in frozen}
    opt = optax.adamw(lr, weight_decay=weight_decay)
    state = opt.init(tp)

    def bag(head, x, m):
        h = head.embed(x)
        u = head.raw_logit(h)
        slide = head.logit(head.add(head.init_state(), h, head.attention_logits(h), m))
        top = jnp.max(jnp.where(m, u, -1e30))
        neg = jnp.sum(jnp.where(m, jax.nn.softplus(u), 0.0)) / jnp.maximum(m.sum(), 1)
        return slide, top, neg

    def loss_fn(tp, x, m, y, full):
        head = head0.replace(params={**tp, **frozen})
        logits, top, neg = jax.vmap(lambda a, b: bag(head, a, b))(x, m)
        slide_loss = optax.sigmoid_binary_cross_entropy(logits, y).mean()
        # instances (MI-Net / CLAM-style): every view of a normal slide is normal; the top view of a tumour slide
        # read whole is tumour. Trains the per-view score and helps when tumour is a few views of thousands.
        pos = jnp.where(full & (y > 0), optax.sigmoid_binary_cross_entropy(top, 1.0), 0.0)
        inst = jnp.where(y > 0, pos, neg).mean()
        return slide_loss + instance_weight * inst

    @jax.jit
    def step(tp, st, x, m, y, full):
        loss, g = jax.value_and_grad(loss_fn)(tp, x, m, y, full)
        upd, st = opt.update(g, st, tp)
        return optax.apply_updates(tp, upd), st, loss

    rng = np.random.default_rng(10_000 + seed)
    curve, losses, best, checkpoints = [], [], head0, []
    attention = None
    flat = np.concatenate([np.asarray(s["features"]) for s in train_slides]) if top_share > 0 else None
    bar = progress_bar(  # a log (not a terminal): a line each tenth, no carriage returns
        range(steps),
        desc=f"{structure['hidden']} units, seed {seed}",
        disable=not progress,
        file=sys.stderr,
        leave=False,
    )
    for i in bar:
        x, m, y, full = batch(rng, train_slides, batch_size, views, attention, top_share)
        tp, state, loss = step(tp, state, x, m, y, full)
        losses.append(float(loss))
        if (i + 1) % eval_every == 0 or i + 1 == steps:
            head = head0.replace(params={**tp, **frozen})
            if top_share > 0 and i + 1 < steps:
                attention = attention_of(head, train_slides, flat=flat)
            row = {"step": i + 1, "loss": float(np.mean(losses[-eval_every:]))}
            if val is not None:
                row.update(val.aucs(head, draws=2))
                row["validation_loss"] = val.log_loss(head)
                checkpoints.append(head)
                bar.set_postfix(loss=f"{row['loss']:.3f}", val=f"{row['full']:.3f}")
            else:
                best = head
            curve.append(row)
    if checkpoints:
        smooth_curve(curve)
        best = checkpoints[max(range(len(curve)), key=lambda i: choice_key(curve[i]))]
    return best, curve


SMOOTH = 1
"""Checks on each side the checkpoint choice averages the validation AUC over (:func:`smooth_curve`)."""


def smooth_curve(curve: list[dict], width: int = SMOOTH) -> list[dict]:
    """Add ``smoothed`` to each row of ``curve``: the mean validation AUC reading everything over the row and its
    ``width`` neighbours on each side (fewer at the ends). On a few validation slides the AUC jumps between checks (a
    fold's curve went 0.17, 1.0, 0.5 ...); one lucky check is no longer chosen over a plateau."""
    full = [r["full"] for r in curve]
    for i, r in enumerate(curve):
        window = [v for v in full[max(0, i - width) : i + width + 1] if v == v]
        r["smoothed"] = float(np.mean(window)) if window else float("nan")
    return curve


def choice_key(row: dict) -> tuple:
    """How a checkpoint is chosen: the highest smoothed validation AUC (:func:`smooth_curve`, rounded to 1e-6 so
    equal plateaus tie), then the lowest validation log loss reading everything, then the higher AUC reading 10 %."""
    sm = row.get("smoothed", row["full"])
    return (round(sm, 6) if sm == sm else -1.0, -row.get("validation_loss", 0.0), row["read 0.1"])


def calibrate(head, val: FlatSet, seed: int = 7):
    """``head`` with Platt scaling fitted on ``val``'s raw logits reading everything and reading random 10 %
    (pooled); returns ``(head, slope)``."""
    raw = head.replace(cal_a=jnp.float32(1.0), cal_b=jnp.float32(0.0))
    rng = np.random.default_rng(seed)
    s = np.concatenate([val.logits(raw), val.logits(raw, val.masks(rng, 0.1))])
    y = np.concatenate([val.labels, val.labels])
    a, b = platt(s, y)
    return head.replace(cal_a=jnp.float32(a), cal_b=jnp.float32(b)), a


def curve_png(curves: dict, title: str) -> bytes:
    """A learning-curve figure (PNG bytes): training loss and validation AUC (reading everything, 10 %) per step,
    one line per candidate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.4))
    for name, rows in curves.items():
        st = [r["step"] for r in rows]
        ax1.plot(st, [r["loss"] for r in rows], label=name)
        if rows and "full" in rows[0]:
            (line,) = ax2.plot(st, [r["full"] for r in rows], label=f"{name}, all read")
            ax2.plot(st, [r["read 0.1"] for r in rows], ls="--", color=line.get_color(), label=f"{name}, 10 % read")
    ax1.set(xlabel="step", ylabel="training log loss (random reads)")
    ax2.set(xlabel="step", ylabel="validation AUC")
    ax1.legend(fontsize=7)
    ax2.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()


# ----------------------------------------------------------------------------- the command
def add_arguments(p) -> None:
    """The options of ``python -m baselines.reading.learned_head_fit``."""
    p.add_argument("--dataset", required=True, help="dataset folder (dataset.json with a train split; feature grids)")
    p.add_argument("--out", help="folder to save the chosen head in (config.json, params.npz, learning_curve.png)")
    p.add_argument("--seed", type=int, default=0, help="training seed (initialisation, batches; default 0)")
    p.add_argument(
        "--val-fraction", type=float, default=0.2, help="share of training slides held out for validation (default 0.2)"
    )
    p.add_argument("--split-seed", type=int, default=0, help="seed of the validation split (default 0, as head_fit)")
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="a dataset built with --folds K: fit on fold I's train side (the other K - 1 folds); "
        "--score: fold I's side of --split",
    )
    p.add_argument(
        "--hidden",
        type=int,
        nargs="+",
        default=[c["hidden"] for c in CANDIDATES],
        help="hidden sizes to try (of %s; default all)" % [c["hidden"] for c in CANDIDATES],
    )
    p.add_argument("--steps", type=int, default=600, help="training steps per candidate (default 600)")
    p.add_argument("--batch", type=int, default=16, help="slides per step (default 16)")
    p.add_argument("--views", type=int, default=512, help="read views kept per slide per step (default 512)")
    p.add_argument(
        "--top-share",
        type=float,
        default=0.5,
        help="share of the kept views taken by the model's highest attention, refreshed every "
        "--eval-every steps (default 0.5; 0 = all drawn uniformly)",
    )
    p.add_argument(
        "--instance-weight",
        type=float,
        default=0.5,
        help="weight of the instance loss beside the slide loss (default 0.5; 0 = slide loss only)",
    )
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--eval-every", type=int, default=50, help="validation scoring every N steps (default 50)")
    p.add_argument(
        "--rotate",
        type=int,
        default=None,
        metavar="SEED",
        help="multiply the features by a fixed random orthogonal matrix drawn from SEED",
    )
    p.add_argument(
        "--score",
        default=None,
        metavar="HEAD",
        type=published_or_path,  # a published head's name: the package's copy first, as histojax evaluate --head
        help="score the saved head HEAD (a folder, or a published head's name: c16-v2-learned-head) on --split "
        "instead of fitting",
    )
    p.add_argument("--split", default="test", help="split --score reads (default test)")
    p.add_argument(
        "--all-folds",
        action="store_true",
        help="a dataset built with --folds K: fit one head per fold, OUT/fold0 ... OUT/fold{K-1} (each as "
        "--fold I --out OUT/foldI)",
    )
    add_flag(p)
    add_restart(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def command_options(args, fold: int | None = None) -> dict:
    """What the command fits (:func:`baselines.reading.fitting.fit_options`; ``fold``: fold I of ``--all-folds``,
    else ``--fold``): compared with a finished head's on a rerun."""
    return fit_options(
        args.dataset,
        args.fold if fold is None else fold,
        **{
            "--seed": args.seed,
            "--val-fraction": args.val_fraction,
            "--split-seed": args.split_seed,
            "--hidden": sorted(args.hidden),
            "--steps": args.steps,
            "--batch": args.batch,
            "--views": args.views,
            "--top-share": args.top_share,
            "--instance-weight": args.instance_weight,
            "--lr": args.lr,
            "--weight-decay": args.weight_decay,
            "--eval-every": args.eval_every,
            "--rotate": args.rotate,
        },
    )


def run(args, parser=None) -> int:
    """Fit (or ``--score``) as the module doc says; prints the figures; exit 2 on a refused dataset or head."""
    if args.score:
        return score_command(args)
    if not args.out:
        return print_error("--out is required to fit a head")
    if getattr(args, "all_folds", False):
        return all_folds_command(args, parser)
    structures = [c for c in CANDIDATES if c["hidden"] in args.hidden]
    if not structures:  # refused before any slide is read
        return print_error(f"--hidden {args.hidden}: none of the candidate sizes {[c['hidden'] for c in CANDIDATES]}")
    t0 = time.perf_counter()
    progress = not args.quiet
    try:
        options = command_options(args)
        if claim_head(args.out, KIND, options, getattr(args, "restart", False)) == "done":
            return 0  # a finished head of this command: kept
        files.check_replaceable(args.out, KIND)  # before any work: a folder of other files is refused now
        spec = read_spec(args.dataset, args.fold)
        warn_scale(args.dataset, spec)  # the encoder-scale warning dataset.json records, repeated
        if not 0.0 < args.val_fraction < 1.0:
            raise FitError(Path(args.dataset) / "dataset.json", f"--val-fraction {args.val_fraction} is not in (0, 1)")
        try:
            kept, held = split_train(spec, args.val_fraction, args.split_seed)
        except ValueError as e:
            raise FitError(Path(args.dataset) / "dataset.json", str(e)) from None
        check_validation_share(
            spec,
            held,
            Path(args.dataset) / "dataset.json",
            args.val_fraction,
            args.fold,
            seed=args.split_seed,
            fitting=MIN_SLIDES_PER_CLASS,
        )
        train_slides = load_split(args.dataset, kept, spec, progress, "training slides")
        val_slides = load_split(args.dataset, held, spec, progress, "validation slides")
        check_classes(args.dataset, train_slides, val_slides)
        check_alike(args.dataset, train_slides + val_slides)
    except (HistojaxDataError, ValueError, OSError) as e:
        return print_error(e)
    q = rotation(args.rotate, train_slides[0]["features"].shape[1]) if args.rotate is not None else None
    train_slides, val_slides = rotate(train_slides, q), rotate(val_slides, q)
    val = FlatSet(val_slides)
    t_load = time.perf_counter() - t0
    results, curves, best = {}, {}, None
    for c in structures:
        name = f"{c['hidden']} units"
        head, curve = train(
            train_slides,
            val,
            c,
            seed=args.seed,
            steps=args.steps,
            batch_size=args.batch,
            views=args.views,
            lr=args.lr,
            weight_decay=args.weight_decay,
            eval_every=args.eval_every,
            top_share=args.top_share,
            instance_weight=args.instance_weight,
            progress=progress,
        )
        top = max(curve, key=choice_key)  # the checkpoint train() returned
        results[name] = {
            **c,
            "best_step": top["step"],
            "validation_auc": round(top["full"], 4),
            "validation_auc_smoothed": round(top["smoothed"], 4),
            "validation_loss": round(top["validation_loss"], 4),
            "validation_auc_read_0.1": round(top["read 0.1"], 4),
        }
        curves[name] = curve
        print(
            f"  {name}: validation {format_auc(top['full'], *val_interval(val, top['full']))} reading everything "
            f"({top['smoothed']:.3f} over "
            f"neighbouring checks), {top['read 0.1']:.3f} reading 10 % (step {top['step']})",
            flush=True,
        )
        if best is None or choice_key(top) > best[0]:
            best = (choice_key(top), name, head)
    _, chosen, head = best
    raw_auc = val.aucs(head, fractions=())["full"]  # before calibration: a negative slope would hide an inversion
    head, slope = calibrate(head, val)
    final = val.aucs(head, fractions=(0.1,), draws=5)
    try:
        check_head(Path(args.dataset) / "dataset.json", raw_auc, slope)
    except FitError as e:
        return print_error(e)
    n_val_tumour = int(sum(s["label"] for s in val_slides))
    if (
        warning := small_split_warning(
            n_val_tumour,
            len(val_slides) - n_val_tumour,
            "the validation share" + (f" of fold {args.fold}" if args.fold is not None else ""),
        )
    ) is not None:
        print(warning, file=sys.stderr)  # the checkpoint and calibration were chosen on it (a refusal stays one line)
    share = "the validation share" + (f" of fold {args.fold}" if args.fold is not None else "")
    if (chance := chance_warning(final["full"], *val_interval(val, final["full"]), share)) is not None:
        print(chance, file=sys.stderr)
    wall = time.perf_counter() - t0
    info = {
        "fitted_on": {
            "dataset": str(Path(args.dataset).resolve()),
            "split": "train (minus validation)",
            "slides": len(train_slides),
            "tumour_slides": int(sum(s["label"] for s in train_slides)),
            "seed": args.seed,
            "rotation_seed": args.rotate,
        },
        "chosen_on": {
            "validation_fraction": args.val_fraction,
            "split_seed": args.split_seed,
            "validation_slides": len(val_slides),
            "candidate": chosen,
            "validation_auc": round(final["full"], 4),
            **dict(
                zip(
                    ("validation_auc_low", "validation_auc_high"),
                    (round(v, 4) for v in val_interval(val, final["full"])),
                )
            ),
            "validation_auc_read_0.1": round(final["read 0.1"], 4),
            **({CHANCE_FLAG: True} if chance is not None else {}),
        },
        "calibration": {
            "slope": round(float(head.cal_a), 5),
            "intercept": round(float(head.cal_b), 5),
            "fitted_on": "validation slides, reading everything and reading random 10 % (pooled)",
        },
        "training": {
            "steps": args.steps,
            "batch_slides": args.batch,
            "views_per_slide": args.views,
            "top_attention_share": args.top_share,
            "instance_weight": args.instance_weight,
            "lr": args.lr,
            "weight_decay": args.weight_decay,
            "optimizer": "adamw",
            "reads": f"all tissue with p={P_FULL}, else {CELL}x{CELL}-view cells at log-uniform [{MIN_READ}, 1]",
        },
        RECORD: fit_record(args.dataset, spec, args.fold, kept, held),
        "candidates": results,
        OPTIONS: options,
        "wall_seconds": round(wall, 1),
        "load_seconds": round(t_load, 1),
        "date": datetime.date.today().isoformat(),
        "jax": jax.__version__,
        "command": "python -m baselines.reading.learned_head_fit " + " ".join(sys.argv[1:]),
    }
    head = head.replace(info=json.dumps(json_safe(info), allow_nan=False))
    try:
        head.save(args.out, extras={"learning_curve.png": curve_png(curves, f"{Path(args.dataset).name}: {head.name}")})
    except (ValueError, HistojaxDataError, OSError) as e:
        return print_error(e)
    print(
        f"validation {format_auc(final['full'], *val_interval(val, final['full']))} reading everything, "
        f"{final['read 0.1']:.3f} reading 10 % ({len(val_slides)} slides); calibration slope {slope:.3f}"
    )
    print(f"chosen: {head.name} ({chosen}); saved to {args.out} in {wall:.0f} s")
    return 0


def val_interval(val, auc: float) -> tuple[float, float]:
    """The 95 % interval over the validation slides of a validation AUC (:func:`data_tools.metrics.auc_interval`)."""
    y = np.asarray(val.labels).astype(bool)
    return auc_interval(auc, int(y.sum()), int((~y).sum()))


def check_head(where, auc: float, slope: float) -> None:
    """Refuse (``FitError`` naming ``where``) a head whose validation AUC (uncalibrated, reading everything) is below
    0.5 or undefined, or whose calibration slope is negative: it ranks or points the wrong way."""
    if not auc >= 0.5:
        raise FitError(
            where, f"the chosen head's validation AUC is {auc:.3f} (< 0.5: it ranks tumour below normal); nothing saved"
        )
    if slope < 0:
        raise FitError(
            where,
            f"the chosen head's calibration slope on validation is {slope:.3f} (negative: its "
            "logit points the wrong way); nothing saved",
        )


def check_classes(dataset, train_slides: list[dict], val_slides: list[dict]) -> None:
    """Refuse (``FitError``) fewer than :data:`MIN_SLIDES_PER_CLASS` training slides of a class, or a validation
    share with one class (its AUC is undefined)."""
    where = Path(dataset) / "dataset.json"
    for cls, what in ((1, "tumour"), (0, "normal")):
        n = sum(int(s["label"] == cls) for s in train_slides)
        if n < MIN_SLIDES_PER_CLASS:
            raise FitError(
                where,
                f"{n} {what} training slides after the validation share is held out; a learned "
                f"head needs at least {MIN_SLIDES_PER_CLASS} of each class",
            )
    if len({int(s["label"]) for s in val_slides}) < 2:
        raise FitError(
            where,
            "the validation share holds one class only (its AUC is undefined); use a larger "
            "--val-fraction or more slides",
        )


def check_alike(dataset, slides: list[dict]) -> None:
    """Refuse slides whose feature vectors differ in length (``FitError`` naming the first that differs)."""
    d = slides[0]["features"].shape[1]
    for s in slides[1:]:
        if s["features"].shape[1] != d:
            raise FitError(
                s["bundle"],
                f"{s['features'].shape[1]}-d features, but {slides[0]['bundle']} has {d}-d: "
                "one head reads one encoder's features",
            )


# ----------------------------------------------------------------------------- scoring a split
def lesion_classes(slides: list[dict]) -> list[str]:
    """Each slide's lesion class as :func:`baselines.reading.slides.lesion_of` defines it (``normal`` for label
    0; ``ITC`` / ``micro`` / ``macro`` by the largest lesion's diameter; ``unknown`` without polygons), the
    annotation read from the bundle's own ``annotations.geojson``."""
    out = []
    for s in slides:
        if not s["label"]:
            out.append("normal")
            continue
        try:
            file = own_file(s["bundle"], "annotations.geojson", "annotation")
            geom = load_annotations(file).tumour
        except HistojaxDataError:
            geom = None
        out.append(lesion_of(geom, s["mpp"])[0])
    return out


def found_counts(logits, classes: list[str]) -> dict[str, int]:
    """Per lesion class present (``ITC``, ``micro``, ``macro``, ``unknown``): how many of its tumour slides score
    above every normal slide of the split (a slide the head finds at any threshold that flags no normal slide).
    ``logits`` ``(N,)``, ``classes`` as :func:`lesion_classes`."""
    logits = np.asarray(logits, float)
    normal = [v for v, c in zip(logits, classes) if c == "normal"]
    top = max(normal) if normal else -np.inf
    return {
        c: int(sum(v > top for v, k in zip(logits, classes) if k == c))
        for c in ("ITC", "micro", "macro", "unknown")
        if c in classes
    }


def found_above_normal(logits, classes: list[str]) -> dict[str, str]:
    """:func:`found_counts` as ``"k/n"`` per lesion class, ``n`` its tumour slides (the readers' lesion table)."""
    return {c: f"{k}/{classes.count(c)}" for c, k in found_counts(logits, classes).items()}


def score_command(args) -> int:
    """``--score HEAD --split S``: AUC of the saved head on split ``S`` reading everything, over all slides and
    without ITC-only slides, and per lesion class the tumour slides found above every normal slide
    (:func:`found_above_normal`), as one JSON line (an AUC one class leaves undefined: ``null`` and a note
    saying so).
    A split of one class is refused in one line naming ``dataset.json`` (its AUC is undefined: one class)."""

    if args.fold is not None:  # the folder of --all-folds (or DIR{fold}): fold I's head
        args.score = head_for_fold(args.score, args.fold)
    try:
        head = LearnedHead.load(args.score)
        spec = read_spec(args.dataset, args.fold)
        warn_scale(args.dataset, spec)
        entries = spec.get(args.split)
        if not isinstance(entries, list) or not entries:
            raise FitError(Path(args.dataset) / "dataset.json", f"has no {args.split!r} split")
        slides = load_split(args.dataset, entries, spec, not args.quiet, f"{args.split} slides")
        if len({s["label"] for s in slides}) < 2:
            raise FitError(
                Path(args.dataset) / "dataset.json",
                f"the {args.split!r} split holds only "
                f"{'tumour' if slides[0]['label'] else 'normal'} "
                f"slides ({len(slides)}): its AUC is {UNDEFINED}; "
                "score a split with tumour and normal slides",
            )
        if slides[0]["features"].shape[1] != head.features_dim:
            raise FitError(
                slides[0]["bundle"],
                f"{slides[0]['features'].shape[1]}-d features; the head reads {head.features_dim}-d",
            )
        if (problem := encoder_mismatch(head, [s.get("encoder") for s in slides])) is not None:
            raise FitError(Path(args.score) / "config.json", f"{problem} ({args.dataset}): fit a head on them")
        allowed = check_scored(head, args.score, args.dataset, entries, getattr(args, "allow_fitting_slides", False))
    except (HistojaxDataError, ValueError, OSError) as e:
        return print_error(e)
    q = rotation(args.rotate, head.features_dim) if args.rotate is not None else None
    flat = FlatSet(rotate(slides, q))
    logits = flat.logits(head)
    classes = lesion_classes(slides)
    keep = np.asarray([c != "ITC" for c in classes])
    y = flat.labels
    every = roc_auc_with_interval(logits, y)
    no_itc = len(set(y[keep].tolist())) == 2  # every tumour slide ITC-only: one class left, the AUC undefined
    kept = roc_auc_with_interval(logits[keep], y[keep])
    counts = {c: classes.count(c) for c in sorted(set(classes))}
    rounded = lambda v: None if not np.isfinite(v) else round(float(v), 4)  # noqa: E731
    record = {
        "head": str(args.score),
        "split": args.split,
        "slides": len(slides),
        "classes": counts,
        "auc": rounded(every["auc"]),
        "auc_low": rounded(every["auc_low"]),
        "auc_high": rounded(every["auc_high"]),
        "auc_without_itc": rounded(kept["auc"]) if no_itc else None,
        "auc_without_itc_low": rounded(kept["auc_low"]) if no_itc else None,
        "auc_without_itc_high": rounded(kept["auc_high"]) if no_itc else None,
        "accuracy": round(float(np.mean((logits > 0) == (y > 0))), 4),
        "found": found_above_normal(logits, classes),
    }
    if allowed:  # --allow-fitting-slides scored slides the head saw: the figure says so
        record["self_scored"] = True
        record["scored_on_seen_slides"] = seen_slides(
            record_of(head_config(head), args.dataset)[0], args.dataset, entries
        )
    if not no_itc:
        record["auc_without_itc_note"] = f"{UNDEFINED} (every tumour slide of the split is ITC-only)"
    where = f"split {args.split!r}" + (f" (fold {args.fold})" if args.fold is not None else "")
    print(
        f"{where}: {format_auc(every['auc'], every['auc_low'], every['auc_high'])} reading everything, over "
        f"{every['n_tumour']} tumour and {every['n_normal']} normal slides",
        file=sys.stderr,
    )
    if (warning := small_split_warning(every["n_tumour"], every["n_normal"], where)) is not None:
        print(warning, file=sys.stderr)
    print(json.dumps(record, allow_nan=False))  # undefined: null, never a bare NaN
    return 0


def all_folds_command(args, parser=None) -> int:
    """``--all-folds --out OUT``: :func:`run` with ``--fold I --out OUT/foldI`` for every fold I of the dataset (its
    ``--folds K``); stops at the first fold refused (its one line). Prints each fold's chosen head."""
    import copy

    from baselines.folds import dataset_folds

    if args.fold is not None:
        return print_error(f"--all-folds fits every fold the dataset records; not with --fold {args.fold}")
    try:
        k, _ = dataset_folds(args.dataset)
        if not 0.0 < args.val_fraction < 1.0:
            raise FitError(Path(args.dataset) / "dataset.json", f"--val-fraction {args.val_fraction} is not in (0, 1)")
        check_all_folds(args.dataset, args.val_fraction, args.split_seed, fitting=MIN_SLIDES_PER_CLASS)  # before any
    except (HistojaxDataError, ValueError, OSError) as e:  # fold is trained: every fold's share is checked now
        return print_error(e)
    out = Path(args.out)
    if getattr(args, "restart", False) and out.is_dir() and not out.is_symlink() and any(out.iterdir()):
        dest = move_head_aside(out)  # the whole set of fold heads, kept together
        print(f"{out}: moved the fold heads there aside to {dest} (--restart); fitting every fold again", flush=True)
    try:
        states = [head_state(out / f"fold{i}", KIND, command_options(args, i)) for i in range(k)]
    except (HistojaxDataError, ValueError, OSError) as e:
        return print_error(e)
    for i, (state, what) in enumerate(states):  # a fold head of another fit: refused before any fold is fitted
        if state == "other":
            return print_error(refusal(out / f"fold{i}", what))
    for i in range(k):
        one = copy.copy(args)
        one.all_folds, one.fold, one.out, one.restart = False, i, str(out / f"fold{i}"), False
        if states[i][0] == "done":
            print(f"fold {i}: finished, kept ({one.out})", flush=True)
            continue
        print(f"fold {i} of {k}: fitting on the other {k - 1} folds -> {one.out}", flush=True)
        code = run(one, parser)
        if code:
            return code
    kept = sum(state == "done" for state, _ in states)
    print(
        f"{'fitted' if not kept else f'kept {kept} finished, fitted {k - kept} of'} {k} heads, one per fold: "
        f"{args.out}/fold0 ... fold{k - 1} (budget-curve / evaluate --all-folds --head {args.out} use fold I's head "
        "on fold I)"
    )
    return 0


def _main():
    return command_main(add_arguments, run, "python -m baselines.reading.learned_head_fit", __doc__)


if __name__ == "__main__":
    raise SystemExit(_main()())
