"""Fit a second slide head (:mod:`histojax.reading.heads.mil`) on a dataset's training slides and choose it on the
validation share: ``python -m baselines.reading.head_mil_fit --dataset DIR --cache FILE.npz --out DIR``.

Data: the finest level's full feature grid ``(H, W, D)`` of every training slide and its tissue views,
read once from the bundles (as :func:`baselines.reading.slides.load_slide` reads them: one row per finest
view) and cached to ``--cache`` (a ``.npz``; re-used when it holds the same slides). The validation share
is :func:`baselines.validation.split_train` with ``--val-fraction`` / ``--seed`` (the same as
:mod:`baselines.reading.head_fit`'s defaults, 0.2 / 0), so the candidates here are scored on the same validation
slides as the published ``c16-v2-head``. The test split is never read.

Candidates (``--candidates``): ``stats`` (:class:`histojax.reading.heads.mil.StatsHead`, :func:`fit_stats`), ``mil-logit``
and ``mil-features`` (:class:`histojax.reading.heads.mil.MilHead`, :func:`train_mil`, ``--steps`` AdamW steps), each fitted
``--seeds`` times on the kept training slides with random reads and scored on the validation share reading
everything and reading random cells (10 %, 20 %); the best mean validation AUC (reading everything) is refitted on
the whole training split (seed 0) and saved to ``--out`` (``config.json`` records every candidate's figures beside
the 2 × 2-mean head's). ``--table FILE`` keeps the validation figures, so a re-run only fits what is missing.
A rerun over a finished head of the same command fits nothing (:func:`baselines.reading.fitting.claim_head`: one
line; a head of other options is refused naming the first difference; ``--restart`` moves it aside to
``OUT.previous-N``).

**Guards**, as :mod:`baselines.reading.head_fit` and :mod:`baselines.reading.learned_head_fit` have them (one line
naming ``dataset.json``, exit 2, no head saved): a validation share with fewer than
:data:`baselines.validation.MIN_VALIDATION_PER_CLASS` slides of a class (before any slide is read); fewer than
:data:`MIN_SLIDES_PER_CLASS` training slides of a class
once the validation share is held back (checked from ``dataset.json``'s labels before any slide is read when it has
them); a chosen candidate whose mean validation AUC (reading everything) is below 0.5 or undefined, or whose
validation slope is negative (:func:`validation_aucs`' ``slope``: the 1-D logistic regression of the labels on its
slide logits; :func:`baselines.reading.fitting.check_head`). The encoder-scale warning ``dataset.json`` records is
repeated (:func:`baselines.reading.slides.warn_scale`). ``config.json`` records what the head was fitted on
(:data:`baselines.reading.provenance.RECORD`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from baselines.reading.fitting import (
    CHANCE_FLAG,
    MIN_SLIDES_PER_CLASS,
    OPTIONS,
    add_restart,
    chance_warning,
    check_classes,
    check_head,
    claim_head,
    fit_options,
    logistic_fit,
)
from baselines.reading.slides import HeadDataError, load_slide, read_spec, spec_label, warn_scale
from data_tools.features import pcam_cnn
from data_tools.metrics import json_safe


def load_grid(bundle, label=None, dim: int = pcam_cnn.VIEW_LOGIT) -> dict:
    """:func:`baselines.reading.slides.load_slide` with ``grid=True`` (read through the checked bundle loader):
    plus ``features (H, W, D)`` float16, the finest feature grid with one row per finest view (the same view →
    feature-cell mapping as ``logits``; ``features[..., dim]`` equals ``logits``)."""
    return load_slide(bundle, label, dim, grid=True)


def cache_grids(dataset, entries, cache, progress: bool = True, extra=None) -> list[dict]:
    """Load the grids of ``entries`` (entries of ``dataset.json``'s lists), or read them from ``cache``
    (``.npz``) when it holds exactly those slides; writes the cache otherwise. Each slide: ``name``,
    ``label``, ``features (H, W, D)`` float16, ``tissue (H, W)`` bool (plus ``extra(slide) -> dict`` of
    arrays / strings stored with it)."""
    dataset, cache = Path(dataset), Path(cache)
    spec = read_spec(dataset)
    names = [Path(e).name for e in entries]
    if cache.is_file():
        z = np.load(cache, allow_pickle=False)
        if list(z["names"]) == names:
            out = []
            for i, n in enumerate(names):
                d = {"name": n, "label": int(z["labels"][i]), "features": z[f"f{i}"], "tissue": z[f"t{i}"]}
                for key in z.files:
                    if key.startswith(f"x{i}_"):
                        d[key[len(f"x{i}_") :]] = z[key]
                out.append(d)
            return out
    out, arrays = [], {}
    for i, rel in enumerate(entries):
        bundle = Path(rel) if Path(rel).is_absolute() else dataset / rel
        s = load_grid(bundle, spec_label(spec, Path(rel).name))
        d = {"name": s["name"], "label": s["label"], "features": s["features"], "tissue": s["tissue"]}
        for key, v in (extra(s) if extra else {}).items():
            d[key] = np.asarray(v)
            arrays[f"x{i}_{key}"] = np.asarray(v)
        arrays[f"f{i}"], arrays[f"t{i}"] = d["features"], d["tissue"]
        out.append(d)
        if progress and (i + 1) % 20 == 0:
            print(f"  loaded {i + 1}/{len(entries)} slides", file=sys.stderr, flush=True)
    cache.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache.with_name(f".{cache.stem}.tmp.npz")
    np.savez(tmp, names=np.asarray(names), labels=np.asarray([d["label"] for d in out]), **arrays)
    tmp.replace(cache)
    return out


# ----------------------------------------------------------------------------- training data, sparse
OFFSETS = (
    -1,
    0,
    1,
    2,
)  # the 4 × 4 window holding every k × k window of histojax.reading.heads.logit.neighbourhood_mean, k ≤ 4
CELL = 4  # random reads pick cells of CELL × CELL views (a reader's cell is about 4 × 4 views)


def window_slots(k: int) -> list[int]:
    """Slots (of the ``OFFSETS × OFFSETS`` neighbour table) inside the ``k × k`` window of
    :func:`histojax.reading.heads.logit.neighbourhood_mean` (rows / columns ``-(k-1)//2 … k//2``)."""
    lo, hi = -((k - 1) // 2), k // 2
    return [
        i * len(OFFSETS) + j
        for i, dy in enumerate(OFFSETS)
        for j, dx in enumerate(OFFSETS)
        if lo <= dy <= hi and lo <= dx <= hi
    ]


def bags(slides: list[dict], dim: int = pcam_cnn.VIEW_LOGIT) -> dict:
    """The tissue views of ``slides`` as one flat set: ``x (N+1, D)`` float32 features (row ``N`` a zero dummy),
    ``seg (N,)`` slide of each view, ``nbr (N, 16)`` row of the tissue view at each offset (``N`` where none),
    ``cell (N,)`` global cell (``CELL × CELL`` views) of each view, ``cell_seg (C,)`` slide of each cell,
    ``labels (B,)``."""
    xs, segs, nbrs, cells, cell_seg = [], [], [], [], []
    base, cbase = 0, 0
    n_total = sum(int(s["tissue"].sum()) for s in slides)
    for b, s in enumerate(slides):
        t = s["tissue"]
        h, w = t.shape
        idx = -np.ones((h + 3, w + 3), np.int64)  # padded by 1 before, 2 after
        ys, xs_ = np.nonzero(t)
        idx[ys + 1, xs_ + 1] = base + np.arange(ys.size)
        nb = np.stack([idx[ys + 1 + dy, xs_ + 1 + dx] for dy in OFFSETS for dx in OFFSETS], 1)
        nbrs.append(np.where(nb < 0, n_total, nb))
        xs.append(np.asarray(s["features"][ys, xs_], np.float32))
        segs.append(np.full(ys.size, b))
        cw = -(-w // CELL)
        cells.append(cbase + (ys // CELL) * cw + xs_ // CELL)
        nc = (-(-h // CELL)) * cw
        cell_seg.append(np.full(nc, b))
        base += ys.size
        cbase += nc
    x = np.concatenate(xs + [np.zeros((1, xs[0].shape[1]), np.float32)])
    return {
        "x": x,
        "logit": x[:, dim],
        "seg": np.concatenate(segs).astype(np.int32),
        "nbr": np.concatenate(nbrs).astype(np.int32),
        "cell": np.concatenate(cells).astype(np.int32),
        "cell_seg": np.concatenate(cell_seg).astype(np.int32),
        "labels": np.asarray([s["label"] for s in slides], np.float32),
        "n": n_total,
        "b": len(slides),
    }


def random_reads(key, data: dict, p_full: float = 0.3, lo: float = 0.02, hi: float = 0.8):
    """``(N,)`` bool random read masks: per slide all tissue (probability ``p_full``) or each cell read with
    probability ``f ~ U(lo, hi)``."""
    import jax
    import jax.numpy as jnp

    k1, k2, k3 = jax.random.split(key, 3)
    f = jax.random.uniform(k1, (data["b"],), minval=lo, maxval=hi)
    f = jnp.where(jax.random.uniform(k2, (data["b"],)) < p_full, 1.01, f)
    u = jax.random.uniform(k3, (data["cell_seg"].shape[0],))
    read_cell = u < f[data["cell_seg"]]
    return read_cell[data["cell"]]


def sparse_instances(head, data: dict, mask):
    """``(N, F)`` the instances of :meth:`histojax.reading.heads.mil.MilHead.instances` for the flat views of ``data``
    under the read mask ``mask (N,)`` (gathered from the neighbour table; equals the dense computation)."""
    import jax.numpy as jnp

    m = jnp.concatenate([mask, jnp.zeros(1, bool)]).astype(jnp.float32)
    nbr = data["nbr"]
    mn = m[nbr]  # (N, 16)
    ln = (data["logit"] * m)[nbr]
    cols = []
    for k in head.ks:
        sl = np.asarray(window_slots(int(k)))
        cols.append(ln[:, sl].sum(1) / jnp.maximum(mn[:, sl].sum(1), 1.0))
    x = jnp.stack(cols, -1)
    if head.inputs == "features":
        sl = np.asarray(window_slots(head.feature_k))
        xf = (data["x"] * m[:, None])[nbr[:, sl]].sum(1) / jnp.maximum(mn[:, sl].sum(1), 1.0)[:, None]
        x = jnp.concatenate([x, xf], -1)
    return x


def init_mil(key, n_in: int, hidden: int = 64, att: int = 32, mu=None, sd=None) -> dict:
    """Initial MilHead parameters (Glorot-uniform weights, zero biases) for ``n_in`` inputs."""
    import jax
    import jax.numpy as jnp

    ks = jax.random.split(key, 5)
    g = jax.nn.initializers.glorot_uniform()
    return {
        "mu": jnp.zeros(n_in) if mu is None else jnp.asarray(mu, jnp.float32),
        "sd": jnp.ones(n_in) if sd is None else jnp.asarray(sd, jnp.float32),
        "w1": g(ks[0], (n_in, hidden)),
        "b1": jnp.zeros(hidden),
        "V": g(ks[1], (hidden, att)),
        "bV": jnp.zeros(att),
        "U": g(ks[2], (hidden, att)),
        "bU": jnp.zeros(att),
        "wa": g(ks[3], (att, 1))[:, 0],
        "wc": g(ks[4], (hidden, 1))[:, 0],
        "bc": jnp.zeros(()),
    }


def train_mil(
    head,
    data: dict,
    seed: int = 0,
    steps: int = 400,
    lr: float = 3e-3,
    weight_decay: float = 1e-4,
    p_full: float = 0.3,
    log_every: int = 0,
):
    """Train ``head`` (a :class:`histojax.reading.heads.mil.MilHead` whose params fix the structure) on the flat
    training views ``data`` (:func:`bags`) with optax AdamW, full batch, a fresh random read mask per slide
    each step (:func:`random_reads`); slide-level log loss. Returns ``(head, losses)``."""
    import jax
    import jax.numpy as jnp
    import optax

    from histojax.reading.heads.mil import attention_pool

    n_in = len(head.ks) + (data["x"].shape[1] if head.inputs == "features" else 0)
    full = jnp.ones(data["n"], bool)
    x_full = sparse_instances(head, data, full)
    mu, sd = x_full.mean(0), x_full.std(0) + 1e-3
    params = init_mil(jax.random.PRNGKey(seed), n_in, head.hidden, mu=mu, sd=sd)
    frozen = {"mu", "sd"}
    opt = optax.adamw(lr, weight_decay=weight_decay)
    train_p = {k: v for k, v in params.items() if k not in frozen}
    state = opt.init(train_p)
    arrays = {k: jnp.asarray(v) for k, v in data.items() if isinstance(v, np.ndarray)}
    d = {**data, **arrays}
    y = arrays["labels"]

    def loss_fn(tp, mask):
        p = {**tp, "mu": mu, "sd": sd}
        x = sparse_instances(head, d, mask)
        logits = attention_pool(p, x, mask, d["seg"], d["b"])
        return optax.sigmoid_binary_cross_entropy(logits, y).mean()

    @jax.jit
    def step(tp, st, key):
        mask = random_reads(key, d, p_full)
        loss, g = jax.value_and_grad(loss_fn)(tp, mask)
        upd, st = opt.update(g, st, tp)
        return optax.apply_updates(tp, upd), st, loss

    key = jax.random.PRNGKey(1000 + seed)
    losses = []
    for i in range(steps):
        key, sub = jax.random.split(key)
        train_p, state, loss = step(train_p, state, sub)
        losses.append(float(loss))
        if log_every and (i + 1) % log_every == 0:
            print(f"    step {i + 1}: loss {np.mean(losses[-log_every:]):.4f}", file=sys.stderr, flush=True)
    p = float(np.clip(data["labels"].mean(), 1e-3, 1 - 1e-3))
    return head.replace(params={**train_p, "mu": mu, "sd": sd}, prior_logit=jnp.float32(np.log(p / (1 - p)))), losses


# ----------------------------------------------------------------------------- the statistics head
def dense_reads(rng, slides: list[dict], shape, fraction: float | None) -> np.ndarray:
    """``(B, H, W)`` bool: each slide's tissue views, all of them (``fraction`` None) or those under cells of
    ``CELL × CELL`` views each read with probability ``fraction``."""
    out = np.zeros((len(slides),) + tuple(shape), bool)
    for i, s in enumerate(slides):
        t = s["tissue"]
        if fraction is not None:
            h, w = t.shape
            u = rng.random((-(-h // CELL), -(-w // CELL))) < fraction
            t = t & np.repeat(np.repeat(u, CELL, 0), CELL, 1)[:h, :w]
        out[i, : t.shape[0], : t.shape[1]] = t
    return out


def padded_logits(slides: list[dict], shape, dim: int = pcam_cnn.VIEW_LOGIT) -> np.ndarray:
    """``(B, H, W)`` float32 view-logit maps padded with 0."""
    out = np.zeros((len(slides),) + tuple(shape), np.float32)
    for i, s in enumerate(slides):
        lg = np.asarray(s["features"][..., dim], np.float32)
        out[i, : lg.shape[0], : lg.shape[1]] = lg
    return out


def fit_stats(
    slides: list[dict],
    shape,
    seed: int = 0,
    masks_per_slide: int = 12,
    l2: float = 1e-2,
    p_full: float = 0.3,
    ks=(1, 2, 3, 4),
):
    """A :class:`histojax.reading.heads.mil.StatsHead` fitted (L2-penalised logistic regression, standardised
    statistics) on ``slides`` read ``masks_per_slide`` times each: all tissue with probability ``p_full``,
    else random cells at a fraction ``U(0.02, 0.8)``."""
    import jax
    import jax.numpy as jnp

    from histojax.reading.heads.mil import StatsHead, statistics_of

    rng = np.random.default_rng(seed)
    stat = jax.jit(jax.vmap(lambda lg, m: statistics_of(lg, m, ks)))
    logits = padded_logits(slides, shape)
    xs, ys = [], []
    y = np.asarray([s["label"] for s in slides], np.float64)
    for _ in range(masks_per_slide):
        fr = [None if rng.random() < p_full else rng.uniform(0.02, 0.8) for _ in slides]
        m = np.stack([dense_reads(rng, [s], shape, f)[0] for s, f in zip(slides, fr)])
        xs.append(np.asarray(stat(logits, m), np.float64))
        ys.append(y)
    x, y = np.concatenate(xs), np.concatenate(ys)
    mu, sd = x.mean(0), x.std(0) + 1e-6
    z = (x - mu) / sd
    w, b = np.zeros(z.shape[1]), 0.0
    for _ in range(4000):
        p = 1.0 / (1.0 + np.exp(-np.clip(z @ w + b, -60, 60)))
        w -= 0.3 * (z.T @ (p - y) / len(y) + l2 * w)
        b -= 0.3 * float(np.mean(p - y))
    pr = float(np.clip(np.mean([s["label"] for s in slides]), 1e-3, 1 - 1e-3))
    params = {
        "mu": jnp.asarray(mu, jnp.float32),
        "sd": jnp.asarray(sd, jnp.float32),
        "w": jnp.asarray(w, jnp.float32),
        "b": jnp.float32(b),
    }
    return StatsHead(params=params, prior_logit=jnp.float32(np.log(pr / (1 - pr))), ks=tuple(ks))


# ----------------------------------------------------------------------------- scoring on validation
def dense_scores(head, slides: list[dict], masks: np.ndarray, shape, chunk: int = 8) -> np.ndarray:
    """The head's slide logits ``(B,)`` through the deployed path (``histojax.reading.heads.score`` on the padded
    feature grids, vmapped, in chunks of ``chunk`` slides)."""
    import jax

    from histojax.reading.heads import score

    f = jax.jit(jax.vmap(lambda g, m: score(head, g, m)))
    out = []
    for i in range(0, len(slides), chunk):
        part = slides[i : i + chunk]
        g = np.zeros((len(part),) + tuple(shape) + (part[0]["features"].shape[-1],), np.float32)
        for j, s in enumerate(part):
            g[j, : s["features"].shape[0], : s["features"].shape[1]] = s["features"]
        m = np.zeros((len(part),) + tuple(shape), bool)
        m[: len(part)] = masks[i : i + chunk]
        out.append(np.asarray(f(g, m)))
    from histojax.reading.heads.files import check_finite_logits

    return check_finite_logits(head, np.concatenate(out))  # one line naming params.npz, never an AUC of NaNs


def validation_aucs(head, slides: list[dict], shape, fractions=(0.1, 0.2), draws: int = 5, seed: int = 123) -> dict:
    """``{"full": AUC reading every tissue view, "slope": the 1-D logistic slope of the labels on those slide logits
    (negative: a higher logit means less tumour), "read 0.1": mean AUC over ``draws`` random cell reads, …}`` of
    ``head`` on ``slides`` (the same masks for every head: ``seed``)."""
    from data_tools.metrics import roc_auc

    y = [s["label"] for s in slides]
    full = dense_scores(head, slides, dense_reads(None, slides, shape, None), shape)
    out = {"full": round(roc_auc(full, y), 4), "slope": round(float(logistic_fit(full, y)[0]), 4)}
    rng = np.random.default_rng(seed)
    for f in fractions:
        aucs = [roc_auc(dense_scores(head, slides, dense_reads(rng, slides, shape, f), shape), y) for _ in range(draws)]
        out[f"read {f:g}"] = round(float(np.mean(aucs)), 4)
    return out


# ----------------------------------------------------------------------------- the command
CANDIDATES = ("stats", "mil-logit", "mil-features")


def candidate_head(name: str, train: list[dict], shape, seed: int, steps: int, data=None):
    """Fit candidate ``name`` (one of ``CANDIDATES``) on ``train`` with ``seed``."""
    from histojax.reading.heads.mil import MilHead

    if name == "stats":
        return fit_stats(train, shape, seed)
    head = MilHead(params={}, inputs="logit" if name == "mil-logit" else "features")
    return train_mil(head, data if data is not None else bags(train), seed=seed, steps=steps)[0]


def add_arguments(p) -> None:
    """The options of ``python -m baselines.reading.head_mil_fit``."""
    p.add_argument("--dataset", required=True, help="dataset folder (dataset.json with a train split; feature grids)")
    p.add_argument("--cache", required=True, help=".npz cache of the training slides' finest feature grids")
    p.add_argument("--out", required=True, help="folder to save the chosen head in (config.json, params.npz)")
    p.add_argument("--candidates", nargs="+", default=list(CANDIDATES), choices=CANDIDATES)
    p.add_argument("--seeds", type=int, default=3, help="fits per candidate (default 3)")
    p.add_argument("--steps", type=int, default=150, help="training steps of the MIL candidates (default 150)")
    p.add_argument(
        "--table",
        default=None,
        help="JSON file of validation results: rows already there are re-used, new rows written to it",
    )
    p.add_argument("--val-fraction", type=float, default=0.2)
    p.add_argument("--seed", type=int, default=0, help="seed of the validation split (default 0, as head_fit)")
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="a dataset built with --folds K: fit on fold I's train side (the other K - 1 folds)",
    )
    add_restart(p)


def command_options(args) -> dict:
    """What the command fits (:func:`baselines.reading.fitting.fit_options`): compared with a finished head's on a
    rerun (``--cache`` and ``--table`` only keep work: not compared)."""
    return fit_options(
        args.dataset,
        args.fold,
        **{
            "--candidates": list(args.candidates),
            "--seeds": args.seeds,
            "--steps": args.steps,
            "--val-fraction": args.val_fraction,
            "--seed": args.seed,
        },
    )


def run(args, parser=None) -> int:
    """Score every candidate × seed on the validation share, choose the best mean full-read AUC, refit it on
    the whole training split (seed 0) and save it."""
    import datetime
    import json
    import time

    import jax

    from baselines.reading.provenance import RECORD, fit_record
    from baselines.validation import check_validation_share, split_train
    from data_tools.cli_output import print_error
    from histojax.reading.heads.files import check_writable
    from histojax.reading.heads.logit import LogitHead
    from histojax.reading.heads.mil import KINDS

    t0 = time.perf_counter()
    try:
        options = command_options(args)
        if claim_head(args.out, KINDS, options, getattr(args, "restart", False)) == "done":
            return 0  # a finished head of this command: kept
        check_writable(args.out)  # a folder that cannot be written: refused before any slide is read
        spec = read_spec(args.dataset, args.fold)
        warn_scale(args.dataset, spec)  # the encoder-scale warning dataset.json records, repeated
        kept, held = split_train(spec, args.val_fraction, args.seed)
        check_validation_share(
            spec,
            held,
            Path(args.dataset) / "dataset.json",
            args.val_fraction,
            args.fold,
            seed=args.seed,
            fitting=MIN_SLIDES_PER_CLASS,
        )
        known = [spec_label(spec, Path(n).name) for n in kept]
        if None not in known:  # labels in dataset.json: too few of a class refused before any slide is read
            check_classes(args.dataset, [{"label": v} for v in known], MIN_SLIDES_PER_CLASS)
        slides = cache_grids(args.dataset, spec["train"], args.cache)
        by = {s["name"]: s for s in slides}
        tr, va = [by[Path(n).name] for n in kept], [by[Path(n).name] for n in held]
        check_classes(args.dataset, tr, MIN_SLIDES_PER_CLASS)
    except (HeadDataError, ValueError, OSError) as e:
        return print_error(e)
    shape = (max(s["tissue"].shape[0] for s in slides), max(s["tissue"].shape[1] for s in slides))
    table_file = Path(args.table) if args.table else None
    table = json.loads(table_file.read_text()) if table_file and table_file.is_file() else {}
    ref = "2x2 mean, max (c16-v2-head)"
    if ref not in table:
        table[ref] = [validation_aucs(LogitHead(k=2, top=1), va, shape)]
    data = None
    for name in args.candidates:
        key = name if name == "stats" else f"{name}, {args.steps} steps"
        rows = table.setdefault(key, [])
        for seed in range(len(rows), args.seeds):
            if name != "stats" and data is None:
                data = bags(tr)
            t = time.perf_counter()
            h = candidate_head(name, tr, shape, seed, args.steps, data)
            rows.append({**validation_aucs(h, va, shape), "seed": seed, "seconds": round(time.perf_counter() - t)})
            print(f"  {key} seed {seed}: {rows[-1]}", file=sys.stderr, flush=True)
            if table_file:
                table_file.write_text(json.dumps(json_safe(table), indent=1, allow_nan=False))
    summary = {
        k: {
            m: [float(np.mean([r[m] for r in v if m in r])), float(np.std([r[m] for r in v if m in r]))]
            for m in {m for r in v for m in r} - {"seed", "seconds"}
        }
        | {"seeds": len(v)}
        for k, v in table.items()
    }  # rows of an older --table may lack "slope": the mean of those that have it
    best = max(
        (k for k in summary if k != ref and k.split(",")[0] in args.candidates), key=lambda k: summary[k]["full"][0]
    )
    from data_tools.metrics import auc_interval, format_auc_runs, small_split_warning

    n_tumour = int(sum(s["label"] for s in va))
    n_normal = len(va) - n_tumour
    print(
        "| candidate | fits | validation AUC, read everything (± std over fits [95 % interval over the validation "
        "slides]) | random 10 % | random 20 % |\n|---|---|---|---|---|"
    )
    for k, v in summary.items():
        low, high = auc_interval(v["full"][0], n_tumour, n_normal)
        print(
            f"| {k} | {v['seeds']} | {format_auc_runs(v['full'][0], v['full'][1], low, high, v['seeds'])} | "
            f"{v['read 0.1'][0]:.3f} | {v['read 0.2'][0]:.3f} |"
        )
    try:  # an inverted or backwards choice is refused before the refit: nothing saved
        check_head(args.dataset, summary[best]["full"][0], summary[best].get("slope", [1.0])[0])
    except HeadDataError as e:
        return print_error(e)
    if (
        warning := small_split_warning(
            n_tumour, n_normal, "the validation share" + (f" of fold {args.fold}" if args.fold is not None else "")
        )
    ) is not None:
        print(warning, file=sys.stderr)  # the candidate was chosen on it (a refusal above stays one line)
    share = "the validation share" + (f" of fold {args.fold}" if args.fold is not None else "")
    chance = chance_warning(
        summary[best]["full"][0], *auc_interval(summary[best]["full"][0], n_tumour, n_normal), share
    )
    if chance is not None:
        print(chance, file=sys.stderr)
    name = best.split(",")[0]
    head = candidate_head(name, slides, shape, 0, args.steps)
    info = {
        "fitted_on": {
            "dataset": str(Path(args.dataset).resolve()),
            "split": "train",
            "slides": len(slides),
            "tumour_slides": int(sum(s["label"] for s in slides)),
            "seed": 0,
            **({"fold": args.fold} if args.fold is not None else {}),
        },
        "chosen_on": {
            "validation_fraction": args.val_fraction,
            "seed": args.seed,
            "train_slides": len(tr),
            "validation_slides": len(va),
            "candidate": best,
            "validation_auc": round(summary[best]["full"][0], 4),
            **dict(
                zip(
                    ("validation_auc_low", "validation_auc_high"),
                    (round(v, 4) for v in auc_interval(summary[best]["full"][0], n_tumour, n_normal)),
                )
            ),
            "reference_validation_auc": summary[ref]["full"][0],
            **({CHANCE_FLAG: True} if chance is not None else {}),
        },
        # refitted on the whole train side: every train slide is a fitting slide, the share validated too
        RECORD: fit_record(args.dataset, spec, args.fold, spec["train"], held),
        "candidates": summary,
        OPTIONS: options,
        "date": datetime.date.today().isoformat(),
        "jax": jax.__version__,
    }
    head = head.replace(info=json.dumps(json_safe(info), allow_nan=False))
    head.save(args.out)
    print(f"chosen: {head.name}; saved to {args.out} in {time.perf_counter() - t0:.0f} s")
    return 0


def _main():
    from data_tools.cli_output import command_main

    return command_main(add_arguments, run, "python -m baselines.reading.head_mil_fit", __doc__)


if __name__ == "__main__":
    raise SystemExit(_main()())
