"""AUC and accuracy against the fraction of the slide read: ``python -m baselines.reading.budget_curve``.

The budget curve is the reading pipeline (:mod:`baselines.reading.pipeline`: one loader, one run loop over readers
× budgets) on the env's glimpse cells, every slide head scoring the views read as a set (:func:`bag_scores`, the
head protocol of :mod:`histojax.reading.heads`). Methods, scored on the test slides of a dataset:

* ``MIL, read everything`` — a gated-attention MIL head (:func:`train_mil`: a ``learned-attention-mil`` head, the
  gated attention of :func:`histojax.reading.heads.mil.attention_pool`) trained once on the *training* slides'
  finest-level tissue views, on every finest-level tissue view (the ceiling; fraction 1);
* ``random reader + MIL`` — glimpse cells picked uniformly at random (``--seeds`` orders);
* ``attention reader + MIL`` — cells picked by the MIL attention on their *low-resolution* features,
  highest first (what the agent could know before reading);
* on pcam-cnn features, the same three rows of the max-logit head (:func:`fit_max_logit`: a logit head, the
  largest view logit read, calibrated), its cells ordered by their own logit (``logit reader + max logit``);
* ``--head DIR`` (a learned head, :mod:`baselines.reading.learned_head_fit`): its rows ``learned head, read
  everything``, ``random reader + learned head`` and ``score reader + learned head`` — cells by the head's per-view
  score of their coarse features, highest first (the score reader);
* ``--ppo NAME RUN`` — a trained policy in a ``glimpse`` or ``zoom_select`` mode, feed-forward
  (``baselines.ppo``) or recurrent (``baselines.ppo_rnn``, detected from its ``config.json``),
  rolled greedily by :func:`baselines.episodes.rollout.run_episodes` at each budget
  (:func:`baselines.reading.pipeline.policy_reads`): its own diagnosis (``NAME``) and every head on what it read
  (``NAME reader + MIL``, ``+ max logit``, ``+ learned head``).

A reader reads cells of ``action_mode=Glimpse(level)`` exactly as the env does
(:func:`baselines.reading.orders.read_cells` follows :meth:`histojax.reading.modes.glimpse.Glimpse.apply`: a cell is
read when it still fits in the budget; the first pick that does not fit ends the episode), at budgets of
``--budgets`` (fractions of the slide's finest-level tissue views). Writes ``budget_curve.csv`` (one row per method ×
budget: mean fraction actually read, AUC, accuracy at 0.5, slides, the standard deviations of AUC and accuracy
over seeds — random reader orders, or the first ``--policy-seeds`` seeds (default 3) of a trained
policy —, ``auc_low`` / ``auc_high`` the AUC's 95 % interval over the slides, ``tumour_slides``, and a trained
policy's fields of view per episode, a column written only when a row has it) and ``budget_curve.png``. It prints
the cells read (:func:`cells_words`); a ``--head``'s rows are the readers' (:func:`head_reader_rows`), so ``readers
--cell-level L`` on the bundle level printed gives the same AUC. A scored split of one class
is refused in one line naming ``dataset.json`` (its AUC is undefined).

``--fold I`` (a dataset built with ``--folds K``): the head trained on fold I's train side, scored on its held-out
side. ``--all-folds``: that for every fold (:func:`fold_rows`), the CSV's rows of each fold (column ``fold``) and one
``fold = mean`` row per method × budget (:func:`summary_rows`: means over folds, ``*_std`` the std over folds); the
plot draws the means with ± bands over folds.

The curve with one slide head with spatial context for every row (overview only, random, scripted and
trained readers, read everything; the CAMELYON lesion table) is ``python -m baselines.reading.readers``
(:mod:`baselines.reading.readers`, the same pipeline on a bundle level's cells).
"""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax.core.scope import LazyRng

from baselines.folds import SUMMARY, dataset_folds, mean_std, scored_side, with_fold
from baselines.reading.csv_files import write_curve_csv
from baselines.reading.orders import attention_order, score_order
from baselines.reading.pipeline import (
    BUDGETS,
    check_two_classes,
    load_split,
    nothing_entries,
    nothing_line,
    policy_reads,
    random_orders,
    read_all,
    reader_auc,
    run_seeds,
    split_words,
)
from baselines.reading.plots import plot_curve
from baselines.reading.provenance import (
    add_flag,
    check_policy,
    check_scored,
    head_for_fold,
    mark_words,
    seen_mark,
    with_seen,
)
from baselines.reading.slides import read_spec
from data_tools.cli_output import command_main, print_error
from data_tools.errors import HistojaxDataError
from data_tools.features import pcam_cnn, pcam_cnn96
from data_tools.metrics import accuracy, auc_interval, format_auc_runs, small_split_warning
from histojax.reading import heads
from histojax.reading.head_reward import pools_views
from histojax.reading.heads.learned import LearnedHead
from histojax.reading.heads.logit import LogitHead
from histojax.reading.heads.mil import attention_pool
from histojax.reading.modes.glimpse import unreadable_warning


def _init_params(key: jax.Array, d: int, hidden: int, attention: int) -> dict:
    """The starting weights: LeCun-normal kernels and zero biases, drawn from ``key`` as flax's ``nn.Dense``
    layers of a module draw them (one key per layer, named ``Dense_0`` … ``Dense_4``), so a seed gives the
    weights the published budget curves started from."""
    init = jax.nn.initializers.lecun_normal()

    def kernel(i, shape):
        return init(LazyRng.create(LazyRng.create(key, f"Dense_{i}"), 1).as_jax_rng(), shape)

    return {
        "w1": kernel(0, (d, hidden)),
        "b1": jnp.zeros(hidden),
        "V": kernel(1, (hidden, attention)),
        "bV": jnp.zeros(attention),
        "U": kernel(2, (hidden, attention)),
        "bU": jnp.zeros(attention),
        "wa": kernel(3, (attention, 1))[:, 0],
        "wc": kernel(4, (hidden, 1))[:, 0],
        "bc": jnp.zeros(()),
    }


def _bag_logits(params: dict, bags: jax.Array, masks: jax.Array) -> jax.Array:
    """Slide logits ``(B,)`` of padded bags ``(B, N, D)`` with validity masks ``(B, N)`` (the training loss's
    batched gated attention, :func:`histojax.reading.heads.mil.attention_pool`)."""
    b, n, d = bags.shape
    return attention_pool(params, bags.reshape(b * n, d), masks.reshape(-1), jnp.repeat(jnp.arange(b), n), b)


def train_mil(
    bags: np.ndarray,
    masks: np.ndarray,
    labels: np.ndarray,
    steps: int = 400,
    lr: float = 3e-3,
    seed: int = 0,
    hidden: int = 64,
    attention: int = 32,
) -> LearnedHead:
    """The "read everything" slide head: a gated-attention MIL (Ilse, Tomczak & Welling, ICML 2018) fitted on
    ``bags (B, N, D)``, ``masks (B, N)``, 0/1 ``labels (B,)`` (full batch, Adam, ``steps`` updates; inputs
    standardised by the valid instances' mean / std, fixed). Returned as the head of kind
    ``learned-attention-mil`` (:class:`~histojax.reading.heads.learned.LearnedHead`: one layer, no calibration,
    the training split's log odds as prior), so it is scored through the head protocol (:func:`bag_scores`)."""
    bags = np.asarray(bags, np.float32)
    masks = np.asarray(masks, bool)
    valid = bags[masks]
    fixed = {"mu": jnp.asarray(valid.mean(0)), "sd": jnp.asarray(valid.std(0) + 1e-6)}
    x, m = jnp.asarray(bags), jnp.asarray(masks)
    y = jnp.asarray(labels, jnp.float32)
    params = _init_params(jax.random.key(seed), bags.shape[-1], hidden, attention)
    opt = optax.adam(lr)
    state = opt.init(params)

    def loss_fn(p):
        return optax.sigmoid_binary_cross_entropy(_bag_logits({**p, **fixed}, x, m), y).mean()

    @jax.jit
    def update(p, s):
        loss, grads = jax.value_and_grad(loss_fn)(p)
        updates, s = opt.update(grads, s, p)
        return optax.apply_updates(p, updates), s, loss

    for _ in range(steps):
        params, state, _ = update(params, state)
    return LearnedHead(
        params={**params, **fixed},
        prior_logit=jnp.float32(_log_odds(labels)),
        features_dim=int(bags.shape[-1]),
        hidden=hidden,
        attention=attention,
        layers=1,
        encoder=None,
    )


def _log_odds(labels) -> float:
    """The log odds of tumour of 0/1 ``labels`` (clipped away from 0 and 1)."""
    p = float(np.clip(np.mean(np.asarray(labels, np.float64)), 1e-3, 1 - 1e-3))
    return float(np.log(p / (1 - p)))


def fit_max_logit(bags: np.ndarray, masks: np.ndarray, labels, dim: int, steps: int = 2000) -> LogitHead:
    """Max-pooling MIL with a fixed instance classifier: the logit head
    (:class:`~histojax.reading.heads.logit.LogitHead`, ``k=1``, ``top=1``) whose slide score is the largest tumour
    logit (feature ``dim``: pcam-cnn holds its view's tumour logit at :data:`PCAM_CNN_VIEW_LOGIT`) of the views
    read. Nothing is learned from slides but the 1-D logistic calibration ``(a, b)`` of ``labels (B,)`` on the
    training ``bags (B, N, D)`` / ``masks (B, N)``' max logits (plain gradient descent, ``steps``), so that scores
    are probabilities (accuracy at 0.5); AUC does not depend on it."""
    x = np.where(masks, bags[..., dim], -1e9).max(axis=-1).astype(np.float64)
    y = np.asarray(labels, np.float64)
    mu, sd = x.mean(), x.std() + 1e-9
    z, w, c = (x - mu) / sd, 0.0, 0.0
    for _ in range(steps):  # plain gradient descent on the mean log loss (convex, 2 parameters)
        p = 1.0 / (1.0 + np.exp(-(w * z + c)))
        w -= 0.5 * float(np.mean((p - y) * z))
        c -= 0.5 * float(np.mean(p - y))
    return LogitHead(
        cal_a=jnp.float32(w / sd),
        cal_b=jnp.float32(c - w * mu / sd),
        prior_logit=jnp.float32(_log_odds(y)),
        dim=int(dim),
        k=1,
        top=1,
        encoder=None,
    )


PCAM_CNN_VIEW_LOGIT = pcam_cnn.VIEW_LOGIT  # 62
"""Index of pcam-cnn's ``mean l`` (the view's tumour logit, its trained output) in its 64-d embedding. Not
``max l`` (63, the most tumour-like 8-px cell's logit): on the 59 test slides of the full v1 set the slide
maximum of ``max l`` over the finest feature grid gives AUC 0.54 (0.457 on the budget curve's tissue views),
that of ``mean l`` 0.865 — a cell's logit is too noisy to take a maximum over ~10^4 views."""


def view_logit_dim(dataset) -> int | None:
    """:data:`PCAM_CNN_VIEW_LOGIT` when ``dataset``'s feature grids are the pcam-cnn family's (``pcam-cnn`` or
    ``pcam-cnn96``, which hold their view logit at the same entry; ``dataset.json``), else None."""
    import json

    try:
        ds = json.loads((Path(dataset) / "dataset.json").read_text())
    except (OSError, ValueError, TypeError):
        return None
    return PCAM_CNN_VIEW_LOGIT if ds.get("encoder") in (pcam_cnn.NAME, pcam_cnn96.NAME) else None


def bags(tables: list[dict], read: list[np.ndarray] | None = None):
    """Padded MIL inputs ``(B, N, D)``, ``(B, N)`` of the slides' instances (only those under the
    ``read[i]`` cells when given; a slide with nothing read has no valid instance, so a head scores it its prior)."""
    chosen = []
    for i, t in enumerate(tables):
        keep = np.ones(len(t["instances"]), bool) if read is None else np.isin(t["instance_cell"], read[i])
        chosen.append(t["instances"][keep])
    n = max(1, max(len(c) for c in chosen))
    d = tables[0]["instances"].shape[1]
    x = np.zeros((len(chosen), n, d), np.float32)
    m = np.zeros((len(chosen), n), bool)
    for i, c in enumerate(chosen):
        x[i, : len(c)] = c
        m[i, : len(c)] = True  # nothing read: no view, and the head scores its prior (as the readers score it)
    return x, m


def bag_scores(head, bags: np.ndarray, masks: np.ndarray) -> np.ndarray:
    """Tumour probabilities ``(B,)`` in ``[0, 1]`` of padded bags ``(B, N, D)`` read where ``masks (B, N)``, by any
    head of the protocol of :mod:`histojax.reading.heads` (:func:`~histojax.reading.heads.score_sets`: each bag a
    set of views, no view with a neighbour, so a logit head pools the views themselves)."""
    logits = heads.score_sets(head, jnp.asarray(bags, jnp.float32), jnp.asarray(masks, bool))
    return np.asarray(jax.nn.sigmoid(logits), np.float64)


MIL_NAMES = ("MIL, read everything", "random reader + MIL", "attention reader + MIL")
MAX_LOGIT_NAMES = ("max view logit, read everything", "random reader + max logit", "logit reader + max logit")
HEAD_NAMES = ("learned head, read everything", "random reader + learned head", "score reader + learned head")
"""The rows of each slide head: reading everything, the random reader, and the reader its cells are ordered by
(the MIL's attention, the max-logit head's view logit, a ``--head``'s per-view score: the score reader)."""


def method_scores(head, tables, budgets=BUDGETS, seeds: int = 5, names=MIL_NAMES, order=None) -> dict:
    """``{(method, budget): (scores (seeds, B), fractions (seeds, B))}`` of every method on ``tables`` through
    ``head`` (:func:`bag_scores`), read by :func:`baselines.reading.pipeline.read_all`; ``names``: the rows' names
    (reading everything, the random reader, the head-ordered reader); ``order(table, head)``: the cell order of
    the last (default: the head's attention when it pools views by attention, else its per-view score)."""
    order = order or (attention_order if pools_views(head) else score_order)
    x, m = bags(tables)
    out = {(names[0], 1.0): (bag_scores(head, x, m)[None], np.ones((1, len(tables))))}
    readers = {names[1]: random_orders(tables, seeds), names[2]: [[order(t, head) for t in tables]]}
    read = read_all(tables, readers, budgets, lambda cells: {"scores": bag_scores(head, *bags(tables, cells))})
    out.update({key: (r["scores"], r["fractions"], r["nothing"]) for key, r in read.items()})
    return out


def rows_from_scores(scores: dict, labels, logits: bool = False, names=None) -> list[dict]:
    """One row per ``(method, budget)`` of ``{(method, budget): (scores (seeds, B), fractions (seeds, B)[, nothing])}``
    (``nothing``: ``{slide index: why it read nothing}``, :func:`baselines.reading.pipeline.read_all`'s): mean
    fraction read, AUC (:func:`baselines.reading.pipeline.reader_auc`, the readers' one AUC: mean and std over seeds,
    ``auc_low`` / ``auc_high`` its 95 % interval over the slides) and accuracy at 0.5 (mean and std over seeds; one
    seed for a deterministic reader). ``logits``: the scores are slide logits (accuracy of their sigmoid).
    ``read_nothing``: the slides (``names``, default their index) read nothing on, and why
    (:func:`baselines.reading.pipeline.nothing_entries`)."""
    rows = []
    for (method, b), (s, f, *why) in scores.items():
        f = np.asarray(f, np.float64)
        nothing = (
            nothing_entries(names if names is not None else range(f.shape[-1]), f, why[0] if why else {})
            if f.ndim == 2
            else []
        )
        auc = reader_auc(s, labels)
        probs = 1 / (1 + np.exp(-np.asarray(s, np.float64))) if logits else s
        accs = np.asarray([accuracy(row, labels) for row in probs])
        rows.append(
            {
                "method": method,
                "budget": float(b),
                "fraction_read": float(f.mean()),
                "auc": auc["auc"],
                "accuracy": float(accs.mean()),
                "slides": len(labels),
                "auc_std": auc["auc_std"],
                "accuracy_std": float(accs.std()),
                "seeds": len(s),
                "fields_of_view": float("nan"),
                "auc_low": auc["auc_low"],
                "auc_high": auc["auc_high"],
                "tumour_slides": auc["n_tumour"],
                "read_nothing": nothing,
            }
        )
    return rows


def glimpse_bundle_level(dataset, env_id: str, level: int, split: str, fold: int | None = None) -> tuple[int, float]:
    """``(bundle level, downsample)`` of scenario level ``level`` of ``env_id`` on ``dataset``'s ``split`` (its first
    bundle): the bundle level whose views are the glimpse cells, and its downsample from the finest scenario level."""
    from data_tools.bundle_files.format import select_levels
    from data_tools.bundle_files.reading import read_metadata
    from histojax.datasets import dataset_slides
    from histojax.registry import spec_of

    bundle = dataset_slides(dataset, split, fold)[0]
    meta = read_metadata(bundle)
    chosen = select_levels(meta, spec_of(env_id).options.n_levels, bundle)
    levels = meta["levels"]
    return int(chosen[level]), float(levels[chosen[level]]["downsample"]) / float(levels[chosen[-1]]["downsample"])


def cells_words(dataset, env_id: str, level: int, split: str = "test", fold: int | None = None) -> str:
    """The cells the curve read, as the readers name theirs: ``"glimpse level 3 of HistoJAX-Medium-v0 = bundle level 2
    (downsample 4, about 4 × 4 finest views a cell)"`` (``readers --cell-level 2`` reads the same cells)."""
    try:
        bundle_level, ds = glimpse_bundle_level(dataset, env_id, level, split, fold)
    except (OSError, ValueError, KeyError, IndexError, HistojaxDataError):
        return f"glimpse level {level} of {env_id}"
    return (
        f"glimpse level {level} of {env_id} = bundle level {bundle_level} (downsample {ds:.3g}, about {ds:.3g} × "
        f"{ds:.3g} finest views a cell)"
    )


def head_reader_rows(head, slides: list[dict], cell_level: int, budgets=BUDGETS, seeds: int = 5) -> list[dict]:
    """The rows :data:`HEAD_NAMES` of a saved head (``--head``), computed by the readers
    (:func:`baselines.reading.reader_scores.scripted_results` on ``slides`` of
    :func:`baselines.reading.pipeline.load_split` with the head, cells of bundle level ``cell_level``; the same
    random orders, reading rule, head scores and AUC, :func:`~baselines.reading.pipeline.reader_auc`), so ``readers
    --cell-level L`` and the curve print the same figures for the same head, slides, budgets and cells."""
    from baselines.reading import reader_scores

    results = reader_scores.scripted_results(
        head,
        slides,
        budgets,
        seeds,
        cell_level,
        only=("read everything", "random reader", reader_scores.score_reader_name(head)),
    )
    names = {
        "read everything": HEAD_NAMES[0],
        "random reader": HEAD_NAMES[1],
        reader_scores.score_reader_name(head): HEAD_NAMES[2],
    }
    labels = np.asarray([s["label"] for s in slides])
    return rows_from_scores(
        {(names[n], b): (r["scores"], r["fractions"], r.get("nothing", {})) for (n, b), r in results.items()},
        labels,
        logits=True,
        names=[s.get("name", i) for i, s in enumerate(slides)],
    )


def budget_rows(
    train,
    test,
    budgets=BUDGETS,
    seeds: int = 5,
    steps: int = 400,
    policies=(),
    dataset=None,
    policy_seeds: int = 3,
    max_dim: int | None = None,
    fold: int | None = None,
    head=None,
    head_cells=None,
):
    """Train the MIL head on ``train = (tables, labels)`` and score every method on ``test`` at ``budgets``
    (with ``max_dim``, the rows of the max-logit head, :func:`fit_max_logit`, on that feature too; with ``head``,
    a saved head that pools views by attention — a learned head, ``--head`` — its rows :data:`HEAD_NAMES`, its
    cells read by its per-view score: the score reader, computed by the readers, :func:`head_reader_rows`, on
    ``head_cells = (the readers' slides of the scored side, bundle level of the cells)``);
    ``policies``: ``(name, run folder)`` of trained PPO policies, rolled on ``dataset``'s test split."""
    mil = train_mil(*bags(train[0]), train[1], steps=steps)
    names = [t.get("name", i) for i, t in enumerate(test[0])]
    rows = rows_from_scores(method_scores(mil, test[0], budgets, seeds), test[1], names=names)
    curve_heads = {"MIL": mil}
    if max_dim is not None:
        top = fit_max_logit(*bags(train[0]), train[1], max_dim)
        rows += rows_from_scores(method_scores(top, test[0], budgets, seeds, MAX_LOGIT_NAMES), test[1], names=names)
        curve_heads["max logit"] = top
    reader_slides = None
    if head is not None:
        if head_cells is None:
            raise ValueError("budget_rows: a head needs head_cells (the readers' slides and cell level)")
        reader_slides, cell_level = head_cells
        rows += head_reader_rows(head, reader_slides, cell_level, budgets, seeds)
        curve_heads["learned head"] = head
    for name, run in policies:
        rows += policy_rows(
            run,
            dataset,
            name,
            curve_heads,
            test[0],
            test[1],
            budgets,
            policy_seeds,
            fold=fold,
            reader_slides=reader_slides,
        )
    return rows


def cross_validated_rows(tables, labels, folds: int, budgets=BUDGETS, seeds: int = 5, steps: int = 400) -> list[dict]:
    """``folds``-fold cross-validation over all slides (for datasets too small for a test split):
    each slide is scored by a head trained on the other folds; AUC and accuracy of the pooled scores."""
    labels = np.asarray(labels)
    fold = np.arange(len(labels)) % folds
    pooled = {}
    for k in range(folds):
        train = [t for t, f in zip(tables, fold) if f != k]
        head = train_mil(*bags(train), labels[fold != k], steps=steps)
        part = method_scores(head, [t for t, f in zip(tables, fold) if f == k], budgets, seeds)
        for key, (s, f, *why) in part.items():
            prev = pooled.get(key)
            if prev is None:
                pooled[key] = (s, f, dict(why[0]) if why else {})
            else:  # the slides of fold k follow those of the folds before: their reasons shift by as many
                moved = {prev[0].shape[1] + i: r for i, r in (why[0] if why else {}).items()}
                pooled[key] = (np.concatenate([prev[0], s], 1), np.concatenate([prev[1], f], 1), {**prev[2], **moved})
    order = np.concatenate([np.flatnonzero(fold == k) for k in range(folds)])
    return rows_from_scores(pooled, labels[order], names=[tables[i].get("name", int(i)) for i in order])


def policy_rows(
    run,
    dataset,
    name: str,
    slide_heads: dict,
    tables,
    labels,
    budgets=BUDGETS,
    policy_seeds: int = 3,
    fold: int | None = None,
    reader_slides=None,
) -> list[dict]:
    """Rows for a trained policy (feed-forward or recurrent, see :func:`policy_reads`) at ``budgets``:
    its own diagnosis (``name``) and each slide head on what it read (``slide_heads``: ``{"MIL": head, ...}``;
    rows ``name reader + MIL``, ``name reader + max logit``, ...), each the mean
    (and ``*_std``) over its first ``policy_seeds`` seeds (as many as the run has, if fewer), with
    the mean fraction read and fields of view per episode. ``reader_slides`` (the readers' slides of the same
    side, :func:`head_reader_rows`): the learned head scores the reads as the readers' ``--reader`` rows do."""
    seeds = max(1, min(policy_seeds, run_seeds(run)))
    per = {}  # (method, budget) -> [(scores (B,), fraction, fields)] per seed
    per_slide, why = {}, {}  # budget -> [fractions (B,) per seed]; (budget, slide) -> why it read nothing
    for seed in range(seeds):
        reasons = {}
        rolled = policy_reads(run, dataset, scored_side(dataset, fold), budgets, seed=seed, fold=fold, why=reasons)
        for key, reason in reasons.items():
            why.setdefault(key, reason)
        for b, reads in rolled.items():
            per_slide.setdefault(float(b), []).append(np.asarray([r[2] for r in reads], np.float64))
            x, m = bags([{**t, "instance_cell": np.arange(len(t["instances"]))} for t in tables], [r[0] for r in reads])
            fraction = float(np.mean([r[2] for r in reads]))
            fields = float(np.mean([r[3] for r in reads]))
            own = np.asarray([r[1] for r in reads])
            scored = [(name, own)] + [
                (f"{name} reader + {h}", _read_scores(h, head, x, m, reads, reader_slides))
                for h, head in slide_heads.items()
            ]
            for method, s in scored:
                per.setdefault((method, float(b)), []).append((s, fraction, fields))
    rows = []
    for (method, b), v in per.items():
        scores = np.stack([s for s, _, _ in v])
        fractions = np.asarray([f for _, f, _ in v], np.float64)
        logits = reader_slides is not None and method.endswith(" + learned head")  # the readers' slide logits
        row = rows_from_scores({(method, b): (scores, fractions)}, labels, logits=logits)[0]
        names = [t.get("name", i) for i, t in enumerate(tables)]
        reasons = {i: r for (bb, i), r in why.items() if bb == b}
        nothing = nothing_entries(names, np.stack(per_slide[b]), reasons)
        rows.append({**row, "fields_of_view": float(np.mean([fv for _, _, fv in v])), "read_nothing": nothing})
    return rows


def _read_scores(which: str, head, x, m, reads, reader_slides) -> np.ndarray:
    """A slide head's scores ``(B,)`` of a policy's reads: the learned head's through the readers' scoring (slide
    logits of :func:`baselines.reading.reader_scores.head_scores` on the read masks) when their slides are given, else
    :func:`bag_scores` (probabilities)."""
    if which != "learned head" or reader_slides is None:
        return bag_scores(head, x, m)
    from baselines.reading import reader_scores

    masks = [reader_scores.masks_from_instances(s, r[0]) for s, r in zip(reader_slides, reads)]
    return np.asarray(reader_scores.head_scores(head, reader_slides, masks), np.float64)


def compute_missing_features(dataset, encoder: str) -> None:
    """Compute the feature grid (``encoder``, float32) of every bundle in ``dataset`` that has none."""
    from data_tools.bundle import read_metadata
    from data_tools.features.grid import compute_features
    from histojax.datasets import dataset_slides

    for bundle in dataset_slides(dataset, "all"):
        if not read_metadata(bundle).get("features"):
            compute_features(bundle, encoder_name=encoder, image_size=None, dtype="float32", progress=False)
            print(f"computed the {encoder} feature grid of {bundle}")


def add_arguments(p) -> None:
    """The options of ``python -m baselines.reading.budget_curve`` and ``histojax budget-curve``."""
    from baselines.published_agents import published_or_path

    p.add_argument(
        "--dataset",
        required=True,
        help="dataset folder with dataset.json (train / test split) whose bundles have feature grids",
    )
    p.add_argument("--env", default="HistoJAX-Medium-v0", help="scenario id (its levels; default HistoJAX-Medium-v0)")
    p.add_argument(
        "--glimpse-level",
        type=int,
        default=3,
        help="scenario level of the glimpse cells (default 3: one above the finest of the 5 levels of "
        "HistoJAX-Medium-v0)",
    )
    p.add_argument(
        "--budgets", type=float, nargs="+", default=list(BUDGETS), help="fractions read (default 5/10/20/50 %%)"
    )
    p.add_argument("--seeds", type=int, default=5, help="random reader orders per slide (default 5)")
    p.add_argument("--steps", type=int, default=400, help="MIL training steps (default 400)")
    p.add_argument(
        "--folds",
        type=int,
        default=0,
        help="K-fold cross-validation over all the dataset's slides instead of its train/test split "
        "(for small datasets; default 0 = use the split)",
    )
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="a dataset built with --folds K: train on fold I's train side, score its test side "
        "(make(..., fold=I)); not with --folds",
    )
    p.add_argument(
        "--all-folds",
        action="store_true",
        help="a dataset built with --folds K: the curve of every fold I = 0 ... K-1 (as --fold I), and "
        "each figure's mean ± std over the folds (per-fold rows and a 'mean' row per method × budget "
        "in the CSV; the plot draws the means); a --ppo RUN holding {fold} is one run per fold",
    )
    p.add_argument(
        "--ppo",
        nargs=2,
        action="append",
        default=[],
        metavar=("NAME", "RUN"),
        help="also a trained policy (run folder of `python -m baselines.ppo` or `python -m baselines.ppo_rnn` "
        "in a glimpse or zoom_select mode) on the test split: its own diagnosis and the MIL head "
        "on what it read",
    )
    p.add_argument(
        "--head",
        default=None,
        metavar="DIR",
        type=published_or_path,
        help="also a saved slide head that pools the views it reads by attention (a learned head: "
        "python -m baselines.reading.learned_head_fit): its rows (read everything, random reader, "
        "score reader: cells by its per-view score of their coarse features), and each --ppo run "
        "scored by it; with --fold I / --all-folds, DIR holding {fold} or the folder of "
        "learned_head_fit --all-folds is fold I's head",
    )
    add_flag(p)
    p.add_argument(
        "--policy-seeds",
        type=int,
        default=3,
        help="seeds of each --ppo run scored (mean ± std; default 3, or as many as the run has)",
    )
    p.add_argument(
        "--compute-features",
        metavar="ENCODER",
        default=None,
        help="first compute the feature grid of every bundle of the dataset that has none with this "
        "encoder (e.g. colour-stats; see `python -m data_tools features --help`)",
    )
    p.add_argument("--out", default="runs/budget_curve", help="output folder (default runs/budget_curve)")


MAX_SEEDS = 1000
"""The most random reader orders (``--seeds``) or policy seeds (``--policy-seeds``) a curve takes."""
MAX_STEPS = 10_000_000
"""The most MIL training steps (``--steps``)."""


def check_options(args) -> str | None:
    """The first problem of the budget curve's options (one line naming the option), or None: budgets in
    ``(0, 1]``, ``--seeds`` / ``--policy-seeds`` in ``[1, MAX_SEEDS]``, ``--steps`` in ``[1, MAX_STEPS]``, ``--folds``
    0 (the dataset's split) or from 2 to the dataset's number of slides, not with ``--fold``; ``--all-folds`` on a
    dataset with folds, not with ``--folds`` or ``--fold``."""
    import math

    if not args.budgets:
        return "--budgets: give at least one fraction of the slide to read, in (0, 1]"
    bad = [b for b in args.budgets if not (math.isfinite(b) and 0 < b <= 1)]
    if bad:
        return f"--budgets: {bad[0]:g} is not a fraction of the slide read; each budget must be in (0, 1]"
    for name, value, top in (
        ("--seeds", args.seeds, MAX_SEEDS),
        ("--policy-seeds", args.policy_seeds, MAX_SEEDS),
        ("--steps", args.steps, MAX_STEPS),
    ):
        if not 1 <= value <= top:
            return f"{name} {value}: must be a whole number from 1 to {top:,}"
    if getattr(args, "all_folds", False):
        if args.folds or args.fold is not None:
            return (
                f"--all-folds scores every fold the dataset records; not with --{'folds' if args.folds else 'fold'}"
                f" {args.folds or args.fold}"
            )
        dataset_folds(args.dataset)  # one line for a dataset without folds
    if args.folds and args.fold is not None:
        return "give --folds K (cross-validation inside the curve) or --fold I (a fold the dataset records), not both"
    if args.folds < 0 or args.folds == 1:
        return f"--folds {args.folds}: give 0 (use the dataset's train / test split) or K >= 2 folds"
    if args.folds:
        from histojax.datasets import dataset_slides

        n = len(dataset_slides(args.dataset, "all"))
        if args.folds > n:
            return (
                f"--folds {args.folds}: {Path(args.dataset) / 'dataset.json'} lists {n} slides, so at most "
                f"{n} folds (each fold needs a slide to score)"
            )
    return None


def load_head(path, tables):
    """The ``--head`` folder's head for the curve (``None`` without one): a head that pools the views it reads by
    attention (a learned head: its rows score views as sets) reading ``tables``' feature length. ``ValueError``, one
    line naming the folder or its ``config.json``, otherwise."""
    if path is None:
        return None
    head = heads.load(path)
    if not pools_views(head):
        raise ValueError(
            f"{Path(path) / 'config.json'}: a {head.kind} head pools neighbourhoods of the view grid; the "
            "budget curve scores the views read as a set: give a learned head (python -m "
            "baselines.reading.learned_head_fit), or score this one with python -m baselines.reading.readers"
        )
    if (problem := heads.encoder_mismatch(head, [t.get("encoder") for t in tables])) is not None:
        raise ValueError(
            f"{Path(path) / 'config.json'}: {problem} (fit a head on them: python -m "
            "baselines.reading.learned_head_fit)"
        )
    d = int(tables[0]["instances"].shape[-1]) if tables else head.features_dim
    if head.features_dim != d:
        raise ValueError(
            f"{Path(path) / 'config.json'}: the head reads {head.features_dim}-d features; the dataset's "
            f"are {d}-d (fit a head on it: python -m baselines.reading.learned_head_fit)"
        )
    return head


def warn_small(labels, where: str) -> None:
    """The small-split warning (:func:`data_tools.metrics.small_split_warning`) of the scored slides' 0/1 ``labels``,
    one line on stderr, when they are too few to rank readers."""
    labels = np.asarray(labels, int)
    warning = small_split_warning(int(labels.sum()), int((1 - labels).sum()), where)
    if warning:
        print(warning, file=sys.stderr)


def fold_rows(args, level: int, fold: int | None):
    """``(rows, train, test)`` of one fold: the head trained on fold ``fold``'s train side, every method scored on
    its held-out side (``fold=None``: the dataset's train / test split); a ``--ppo`` run folder holding ``{fold}``
    is that fold's run. ``train``, ``test``: ``(tables, labels)`` of :func:`baselines.reading.pipeline.load_split`.
    A held-out side of one class is refused (:func:`baselines.reading.pipeline.check_two_classes`)."""
    side = scored_side(args.dataset, fold)
    head_dir = getattr(args, "head", None)
    if head_dir is not None and fold is not None:
        head_dir = head_for_fold(
            head_dir, fold
        )  # --head DIR of learned_head_fit --all-folds, or RUN{fold}: fold's head
    mark = {}
    if head_dir is not None:  # a head fitted or validated on a scored slide: refused before any slide is read
        scored = read_spec(args.dataset, fold).get(side) or []
        check_scored(
            heads.load(head_dir), head_dir, args.dataset, scored, getattr(args, "allow_fitting_slides", False)
        )  # --allow-fitting-slides: a warning, and the rows say so (scored_on_seen_slides)
        mark = seen_mark(heads.load(head_dir), args.dataset, scored)
    policies = [(name, run if fold is None else with_fold(run, fold)) for name, run in args.ppo]
    if policies:  # a policy trained on a scored slide: refused too, before any slide is read
        scored = read_spec(args.dataset, fold).get(side) or []
        for name, run in policies:
            names = check_policy(
                run, args.dataset, scored, getattr(args, "allow_fitting_slides", False), option=f"--ppo {name}"
            )
            mark = with_seen(mark, f"policy {name}", names)
    test = load_split(args.dataset, side, env_id=args.env, level=level, fold=fold)
    check_two_classes(args.dataset, side, test.labels, fold)
    if (
        line := unreadable_warning(
            [t.get("name", i) for i, t in enumerate(test.tables)],
            [t["cell_views"] for t in test.tables],
            [t["valid"] for t in test.tables],
            [t["total"] for t in test.tables],
            args.budgets,
            "" if fold is None else f"fold {fold}",
        )
    ) is not None:
        print(f"warning: {line}", file=sys.stderr, flush=True)  # a budget below every cell: the overview alone
    train = load_split(args.dataset, "train", env_id=args.env, level=level, fold=fold)
    head = load_head(head_dir, test.tables)
    head_cells = None
    if head is not None:  # the head's rows come from the readers, on the same cells (the glimpse level's bundle level)
        cell_level = glimpse_bundle_level(args.dataset, args.env, level, side, fold)[0]
        mine = load_split(args.dataset, side, fold=fold, head=head, cell_level=cell_level)
        if [s["label"] for s in mine.slides] != [int(v) for v in test.labels]:
            raise ValueError(
                f"{Path(args.dataset) / 'dataset.json'}: the readers' and the env's {side!r} slides differ"
            )
        head_cells = (mine.slides, cell_level)
    rows = budget_rows(
        (train.tables, train.labels),
        (test.tables, test.labels),
        args.budgets,
        seeds=args.seeds,
        steps=args.steps,
        policies=policies,
        dataset=args.dataset,
        policy_seeds=args.policy_seeds,
        max_dim=view_logit_dim(args.dataset),
        fold=fold,
        head=head,
        head_cells=head_cells,
    )
    if mark:  # scored with --allow-fitting-slides on slides the head or a policy saw: each row says which
        rows = [{**r, "scored_on_seen_slides": mark_words(mark)} for r in rows]
    if not getattr(args, "all_folds", False):  # once scored (a refusal stays one line); --all-folds: curve_rows warns
        warn_small(test.labels, split_words(args.dataset, side, fold))  # fold I's held-out slides, or the split
    return rows, (train.tables, train.labels), (test.tables, test.labels)


def summary_rows(rows: list[dict]) -> list[dict]:
    """One ``fold = "mean"`` row per method × budget of per-fold ``rows`` (each with a ``fold``): the mean over folds
    of the fraction read, AUC, accuracy and fields of view, ``auc_std`` / ``accuracy_std`` their standard deviation
    over folds (not over seeds), ``slides`` the slides scored over all folds, ``seeds`` those of one fold;
    ``auc_low`` / ``auc_high`` the 95 % interval of the mean AUC over the pooled held-out slides of all folds, each
    slide once (:func:`data_tools.metrics.auc_interval` with the tumour and normal slides of every fold added)."""
    groups: dict = {}
    for r in rows:
        groups.setdefault((r["method"], r["budget"]), []).append(r)
    out = []
    for (method, budget), rs in groups.items():
        (auc, auc_std), (acc, acc_std) = (mean_std([r[m] for r in rs]) for m in ("auc", "accuracy"))
        slides = sum(r["slides"] for r in rs)
        tumour = sum(r["tumour_slides"] for r in rs) if all("tumour_slides" in r for r in rs) else None
        low, high = auc_interval(auc, tumour, slides - tumour) if tumour is not None else (float("nan"),) * 2
        out.append(
            {
                "fold": SUMMARY,
                "method": method,
                "budget": budget,
                "auc_low": low,
                "auc_high": high,
                **({"tumour_slides": tumour} if tumour is not None else {}),
                "fraction_read": mean_std([r["fraction_read"] for r in rs])[0],
                "auc": auc,
                "accuracy": acc,
                "slides": sum(r["slides"] for r in rs),
                "auc_std": auc_std,
                "accuracy_std": acc_std,
                "seeds": max(r["seeds"] for r in rs),
                "fields_of_view": mean_std([r["fields_of_view"] for r in rs])[0],
            }
        )
    return out


def curve_rows(args, level: int) -> tuple[list[dict], str]:
    """``(rows, what was scored)`` of the curve's options: ``--folds K`` cross-validation over all slides,
    ``--all-folds`` every fold and the means, else the split (or ``--fold I``)."""
    if args.folds:
        every = load_split(args.dataset, "all", env_id=args.env, level=level)
        check_two_classes(args.dataset, "all", every.labels)
        if getattr(args, "head", None):
            raise ValueError("--head: not with --folds (cross-validation trains its own MIL on each fold)")
        rows = cross_validated_rows(
            every.tables, every.labels, args.folds, args.budgets, seeds=args.seeds, steps=args.steps
        )
        return rows, f"{len(every.labels)} slides, {args.folds}-fold cross-validation"
    if getattr(args, "all_folds", False):
        k = dataset_folds(args.dataset)[0]
        rows, scored, pooled = [], 0, []
        for i in range(k):
            print(f"fold {i} of {k} (0 to {k - 1}) ...", flush=True)
            part, _, test = fold_rows(args, level, i)
            rows += [{"fold": i, **r} for r in part]
            scored += len(test[1])
            pooled.extend(int(v) for v in test[1])
        warn_small(pooled, f"the {k} folds' held-out slides together")
        rows += summary_rows(rows)
        return rows, f"mean ± std over {k} folds ({scored} slides scored)"
    rows, train, test = fold_rows(args, level, args.fold)
    return rows, f"{len(train[1])} train / {len(test[1])} test slides"


def run(args, parser=None) -> int:
    """The budget curve on parsed ``args``: CSV and PNG in ``args.out``. Bad options: one line, exit 2
    (:func:`check_options`)."""
    level = args.glimpse_level
    try:
        problem = check_options(args)
    except (HistojaxDataError, ValueError) as e:
        return print_error(e)
    if problem:
        return print_error(problem)
    if args.compute_features:
        compute_missing_features(args.dataset, args.compute_features)
    try:
        rows, split = curve_rows(args, level)
    except (HistojaxDataError, ValueError) as e:  # e.g. a scored split of one class: its AUC is undefined
        return print_error(e)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = write_curve_csv(rows, out / "budget_curve.csv")
    title = f"{Path(args.dataset).name}: {split}, glimpse level {level} of {args.env}"
    shown = [r for r in rows if r.get("fold", SUMMARY) == SUMMARY]  # --all-folds: the means over folds
    png = plot_curve(shown, out / "budget_curve.png", title)
    if len(shown) < len(rows):
        print(f"mean ± std over folds (the rows of each fold: {csv_path})")
    fields = any(np.isfinite(r.get("fields_of_view", float("nan"))) for r in shown)  # no always-empty column
    print(f"cells: {cells_words(args.dataset, args.env, level, scored_side(args.dataset, args.fold), args.fold)}")
    print(
        f"{'method':32s} {'budget':>6s} {'read':>6s} {'AUC ± std over seeds [95 % interval over slides]':>44s} "
        f"{'acc':>15s}" + (f" {'fields':>6s}" if fields else "")
    )
    for r in shown:
        auc = format_auc_runs(
            r["auc"],
            r["auc_std"],
            r.get("auc_low", float("nan")),
            r.get("auc_high", float("nan")),
            max(r["seeds"], 2 if r.get("fold") == SUMMARY else 1),
        )
        print(
            f"{r['method']:32s} {r['budget']:6.2f} {r['fraction_read']:6.3f} {auc:>44s} "
            f"{r['accuracy']:6.3f} ± {r['accuracy_std']:5.3f}" + (f" {r['fields_of_view']:6.1f}" if fields else "")
        )
    for r in rows:  # a row that read nothing on some slides: which, and why
        line = nothing_line(r["method"], r["budget"], r.get("read_nothing") or [])
        if line:
            where = "" if r.get("fold", SUMMARY) == SUMMARY else f"fold {r['fold']}: "
            print(f"warning: {where}{line}")
    print(f"wrote {csv_path} and {png}")
    return 0


main = command_main(add_arguments, run, "python -m baselines.reading.budget_curve", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
