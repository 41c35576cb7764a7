"""Readers' read masks scored through one slide head: the library of the readers command
(:mod:`baselines.reading.readers`), the navigators' diagnosis (:mod:`baselines.reading.diagnosis`) and the budget
curve's head rows (:mod:`baselines.reading.budget_curve`).

* cells and masks: :func:`cell_table` (a bundle level's cells over the finest views), :func:`tumour_views`,
  :func:`masks_from_instances`, :func:`policy_masks` (a trained reader's read masks);
* scores: :func:`head_scores` (the head's slide logits on read masks), :func:`terms_scores`, :func:`overview_scores`;
* results: :func:`new_results`, :func:`add_reader`, :func:`scripted_results` (overview, random, logit / score,
  search, read everything), :func:`rows_from_results`, :func:`csv_rows`, :func:`print_tables`;
* the split: :func:`load_split` (head and slides), :func:`cells_words`, :func:`unreadable_line`.
"""

from __future__ import annotations

import sys

import jax
import numpy as np

from baselines.reading import pipeline
from baselines.reading.orders import logit_order, search_order
from baselines.reading.pipeline import BUDGETS, reader_auc
from baselines.reading.slides import CLASSES, lesion_class, padded
from data_tools.metrics import accuracy, format_auc_runs
from histojax.reading.head_reward import pools_views
from histojax.reading.heads import score_batch
from histojax.reading.heads.files import check_finite_logits

KINDS = ("overview", "random", "scripted", "learned", "everything")


def tumour_views(slide: dict) -> np.ndarray:
    """``(H, W)`` bool: the finest views that overlap the slide's tumour polygons."""
    import shapely

    h, w = slide["tissue"].shape
    out = np.zeros((h, w), bool)
    geom, t = slide.get("tumour"), slide["tile"]
    if geom is None or geom.is_empty:
        return out
    x0, y0, x1, y1 = geom.bounds
    gx = np.arange(max(0, int(x0 // t)), min(w, int(x1 // t) + 1))
    gy = np.arange(max(0, int(y0 // t)), min(h, int(y1 // t) + 1))
    if gx.size == 0 or gy.size == 0:
        return out
    yy, xx = np.meshgrid(gy, gx, indexing="ij")
    boxes = shapely.box(xx.ravel() * t, yy.ravel() * t, (xx.ravel() + 1) * t, (yy.ravel() + 1) * t)
    shapely.prepare(geom)
    hit = shapely.intersects(boxes, geom) & (shapely.area(shapely.intersection(boxes, geom)) > 0)
    out[yy.ravel()[hit], xx.ravel()[hit]] = True
    return out


def cell_table(slide: dict, level: int) -> dict:
    """The slide's cells at bundle level ``level``: ``cell (H, W)`` int64 cell of each finest view,
    ``cell_views (C,)`` tissue views under each cell, ``valid (C,)``, ``logit (C,)`` the cell's own
    low-resolution logit, ``grid (h, w)``, ``total`` tissue views."""
    coarse = slide["coarse"][level]
    ch, cw = coarse.shape
    step = slide["stride"] * slide["downsample"][level]  # finest px per cell
    h, w = slide["tissue"].shape
    cy = np.clip(((np.arange(h) + 0.5) * slide["tile"] // step).astype(np.int64), 0, ch - 1)  # cell of the centre
    cx = np.clip(((np.arange(w) + 0.5) * slide["tile"] // step).astype(np.int64), 0, cw - 1)
    cell = cy[:, None] * cw + cx[None, :]
    counts = np.bincount(cell[slide["tissue"]], minlength=ch * cw)
    return {
        "cell": cell,
        "cell_views": counts,
        "valid": counts > 0,
        "logit": coarse.reshape(-1).astype(np.float64),
        "grid": (ch, cw),
        "total": max(1, int(slide["tissue"].sum())),
    }


def masks_from_instances(slide: dict, instances) -> np.ndarray:
    """A read mask ``(H, W)`` from indices into the slide's tissue views in raster order (what
    :meth:`histojax.reading.modes.glimpse.Glimpse.host_tables` calls ``instances`` and
    :func:`baselines.reading.pipeline.policy_reads` returns as ``read``)."""
    flat = np.flatnonzero(slide["tissue"].reshape(-1))
    mask = np.zeros(slide["tissue"].size, bool)
    mask[flat[np.asarray(instances, np.int64)]] = True
    return mask.reshape(slide["tissue"].shape)


def policy_masks(
    run,
    dataset,
    slides: list[dict],
    split: str = "test",
    budgets=BUDGETS,
    seeds: int = 3,
    fold: int | None = None,
    why: dict | None = None,
) -> dict:
    """A trained ``glimpse`` / ``zoom_select`` policy's read masks, ``{budget: [masks per slide] per seed}``
    (its first ``seeds`` seeds, rolled greedily by :func:`baselines.reading.pipeline.policy_reads` on
    ``dataset``'s ``split``, whose slides ``slides`` are, in the same order): ready for :func:`add_reader`.
    ``why`` (a dict): filled with ``{budget: {slide index: why it read nothing}}`` (``add_reader``'s ``nothing``)."""
    out = {float(b): [] for b in budgets}
    for seed in range(max(1, min(seeds, pipeline.run_seeds(run)))):
        reasons = {}
        for b, reads in pipeline.policy_reads(run, dataset, split, budgets, seed=seed, fold=fold, why=reasons).items():
            if len(reads) != len(slides):
                raise ValueError(f"{run}: {len(reads)} episodes for {len(slides)} slides of split {split!r}")
            out[float(b)].append([masks_from_instances(s, r[0]) for s, r in zip(slides, reads)])
        if why is not None:  # the first seed that read nothing on a slide says why
            for (b, i), reason in reasons.items():
                why.setdefault(float(b), {}).setdefault(i, reason)
    return out


def padded_terms(terms: list[np.ndarray]) -> np.ndarray:
    """``(B, Hmax, Wmax, 2)`` stack of per-view term grids ``(H, W, 2)`` padded with 0 at the bottom / right."""
    h, w = max(t.shape[0] for t in terms), max(t.shape[1] for t in terms)
    out = np.zeros((len(terms), h, w, 2), np.float32)
    for i, t in enumerate(terms):
        out[i, : t.shape[0], : t.shape[1]] = t
    return out


def terms_scores(head, terms: list[np.ndarray], masks: list[np.ndarray]) -> np.ndarray:
    """An attention-pooling head's slide logits ``(B,)`` from cached per-view terms ``(H, W, 2)`` read where
    ``masks (H, W)`` (:meth:`~histojax.reading.heads.learned.LearnedHead.score_terms`)."""
    return check_finite_logits(
        head, jax.jit(jax.vmap(head.score_terms))(padded_terms(terms), padded(list(masks), False))
    )


def head_scores(head, slides: list[dict], masks: list[np.ndarray]) -> np.ndarray:
    """The head's slide logits ``(B,)`` on ``masks`` (a head that reads every feature entry: from the slides'
    cached ``terms``, :func:`with_head_scores`)."""
    if pools_views(head):
        return terms_scores(head, [s["terms"] for s in slides], masks)
    return check_finite_logits(
        head, score_batch(head, padded([s["logits"] for s in slides], 0.0), padded(list(masks), False))
    )


def overview_scores(head, slides: list[dict], level: int) -> np.ndarray:
    """The head on each slide's cell-level logits over its valid cells (nothing of the finest level read)."""
    logits, masks = [], []
    for s in slides:
        c = cell_table(s, level)
        logits.append(s["coarse"][level].astype(np.float32))
        masks.append(c["valid"].reshape(c["grid"]))
    if pools_views(head):  # the head on the cells' own coarse feature vectors
        return terms_scores(head, [s["coarse_terms"][level] for s in slides], masks)
    return check_finite_logits(head, score_batch(head, padded(logits, 0.0), padded(masks, False)))


def new_results() -> dict:
    """An empty results record: ``{(reader, budget): {"kind", "scores" (seeds, B), "fractions" (seeds, B),
    "tumour_read" (seeds, B) bool}}``."""
    return {}


def add_reader(
    results: dict,
    head,
    slides: list[dict],
    name: str,
    masks_by_budget: dict,
    kind: str = "learned",
    tumour: list[np.ndarray] | None = None,
    nothing: dict | None = None,
) -> dict:
    """Score a reader's read masks with ``head`` and add its rows to ``results``.

    ``masks_by_budget``: ``{budget: [masks of seed 0, masks of seed 1, ...]}``, each a list of ``(H, W)``
    bool read masks, one per slide of ``slides`` (a learned reader: one list per training seed or rollout);
    ``kind``: one of ``KINDS`` (colour family of the plot). The fraction read is measured from the masks.
    ``nothing``: ``{budget: {slide index: why it read nothing}}`` (:func:`policy_masks`' ``why``)."""
    tumour = tumour if tumour is not None else [tumour_views(s) for s in slides]
    total = np.asarray([max(1, int(s["tissue"].sum())) for s in slides])
    for budget, per_seed in masks_by_budget.items():
        per_seed = [per_seed] if isinstance(per_seed[0], np.ndarray) else per_seed
        scores, fractions, found = [], [], []
        for masks in per_seed:
            masks = [np.asarray(m, bool) & s["tissue"] for m, s in zip(masks, slides)]
            scores.append(head_scores(head, slides, masks))
            fractions.append(np.asarray([m.sum() for m in masks]) / total)
            found.append(np.asarray([bool((m & t).any()) for m, t in zip(masks, tumour)]))
        results[(name, float(budget))] = {
            "kind": kind,
            "scores": np.stack(scores),
            "fractions": np.stack(fractions),
            "tumour_read": np.stack(found),
            "nothing": dict((nothing or {}).get(float(budget), {})),
        }
    return results


def score_reader_name(head) -> str:
    """``"score reader"`` for a head that reads every feature entry (cells by its per-view score of their coarse
    features), ``"logit reader"`` for a logit head (its per-view score is the feature entry it reads)."""
    return "score reader" if pools_views(head) else "logit reader"


def unreadable_line(slides: list[dict], tables: list[dict], budgets) -> str | None:
    """The line (:func:`histojax.reading.modes.glimpse.unreadable_warning`) naming the slides where some of
    ``budgets`` reads no cell of ``tables`` (:func:`cell_table`), with the nearest budget that reads one on every
    slide; ``None`` when every budget reads something everywhere."""
    from histojax.reading.modes.glimpse import unreadable_warning

    return unreadable_warning(
        [s.get("name", i) for i, s in enumerate(slides)],
        [t["cell_views"] for t in tables],
        [t["valid"] for t in tables],
        [t["total"] for t in tables],
        budgets,
    )


def scripted_results(
    head, slides: list[dict], budgets=BUDGETS, seeds: int = 5, level: int = 3, progress: bool = False, only=None
) -> dict:
    """The reference rows: overview only, random reader (``seeds`` orders), logit (score) reader, search reader,
    read everything; the readers' orders read at every budget by the pipeline's run loop
    (:func:`baselines.reading.pipeline.read_all`) and their read masks scored by ``head`` (:func:`head_scores`).
    ``only``: the names of the rows wanted (default all)."""
    want = (lambda name: True) if only is None else (lambda name: name in only)  # noqa: E731
    results = new_results()
    tumour = [tumour_views(s) for s in slides]
    n = len(slides)
    if want("overview only"):
        results[("overview only", 0.0)] = {
            "kind": "overview",
            "scores": overview_scores(head, slides, level)[None],
            "fractions": np.zeros((1, n)),
            "tumour_read": np.zeros((1, n), bool),
        }
    if want("read everything"):
        add_reader(
            results, head, slides, "read everything", {1.0: [[s["tissue"] for s in slides]]}, "everything", tumour
        )
    tables = [cell_table(s, level) for s in slides]
    if (line := unreadable_line(slides, tables, budgets)) is not None:
        print(f"warning: {line}", file=sys.stderr, flush=True)
    top = max(budgets)
    readers = {
        "random reader": lambda: pipeline.random_orders(tables, seeds),
        score_reader_name(head): lambda: [[logit_order(c) for c in tables]],
        "search reader": lambda: [[search_order(s, c, limit=top + 0.01) for s, c in zip(slides, tables)]],
    }
    readers = {name: orders() for name, orders in readers.items() if want(name)}
    kinds = {name: "random" if name == "random reader" else "scripted" for name in readers}

    def score(cells: list[np.ndarray]) -> dict:
        masks = [np.isin(c["cell"], r) & s["tissue"] for c, r, s in zip(tables, cells, slides)]
        return {
            "scores": head_scores(head, slides, masks),
            "tumour_read": np.asarray([bool((m & t).any()) for m, t in zip(masks, tumour)]),
        }

    results.update(pipeline.read_all(tables, readers, budgets, score, kinds, progress=progress))
    return results


def rows_from_results(results: dict, slides: list[dict]) -> list[dict]:
    """One row per ``(reader, budget)``: fraction read (mean, min, 10/50/90th percentiles, max over episodes),
    AUC over all slides and without ITC-only slides, accuracy at 0.5 (mean ± std over seeds; ``auc_per_seed``
    each seed's AUC, kept in ``readers.json``: what a seed is chosen by on validation), ``read_nothing`` the slides
    it read nothing on and why (:func:`baselines.reading.pipeline.nothing_entries`; the overview reads nothing by
    design), and per lesion class the slides on which the reader read tumour and those the head found (mean over
    seeds)."""
    labels = np.asarray([s["label"] for s in slides])
    names = [s.get("name", i) for i, s in enumerate(slides)]
    classes = [lesion_class(s)[0] for s in slides]
    no_itc = np.asarray([c != "ITC" for c in classes])
    rows = []
    for (name, b), r in results.items():
        s, f, t = r["scores"], r["fractions"], r["tumour_read"]
        every, kept = reader_auc(s, labels), reader_auc(s[:, no_itc], labels[no_itc])
        accs = np.asarray([accuracy(1 / (1 + np.exp(-x)), labels) for x in s])
        row = {
            "reader": name,
            "kind": r["kind"],
            "budget": b,
            "seeds": len(s),
            "slides": len(labels),
            "fraction_read": float(f.mean()),
            "fraction_min": float(f.min()),
            "fraction_p10": float(np.percentile(f, 10)),
            "fraction_median": float(np.median(f)),
            "fraction_p90": float(np.percentile(f, 90)),
            "fraction_max": float(f.max()),
            "auc": every["auc"],
            "auc_std": every["auc_std"],
            "auc_low": every["auc_low"],
            "auc_high": every["auc_high"],
            "auc_no_itc": kept["auc"],
            "auc_no_itc_std": kept["auc_std"],
            "auc_no_itc_low": kept["auc_low"],
            "auc_no_itc_high": kept["auc_high"],
            "accuracy": float(accs.mean()),
            "accuracy_std": float(accs.std()),
            "auc_per_seed": [round(float(a), 4) for a in every["auc_per_run"]],
            "read_nothing": [] if r["kind"] == "overview" else pipeline.nothing_entries(names, f, r.get("nothing", {})),
        }
        for c in CLASSES:
            idx = np.asarray([k == c for k in classes])
            top_normal = (
                s[:, labels == 0].max(1, keepdims=True) if (labels == 0).any() else np.full((len(s), 1), -np.inf)
            )
            row[f"{c}_slides"] = int(idx.sum())
            row[f"{c}_tumour_read"] = float(t[:, idx].sum(1).mean()) if idx.any() else 0.0
            row[f"{c}_found"] = float((s[:, idx] > top_normal).sum(1).mean()) if idx.any() else 0.0
        rows.append(row)
    return rows


def csv_rows(rows: list[dict]) -> list[dict]:
    """``rows`` (:func:`rows_from_results`) as ``readers.csv`` holds them: one number per cell (the per-seed
    lists and the slides read nothing on stay in ``readers.json``)."""
    return [{k: v for k, v in r.items() if k not in ("auc_per_seed", "read_nothing")} for r in rows]


def nothing_lines(rows: list[dict]) -> list[str]:
    """One line per row (:func:`rows_from_results`) that read nothing on some slides, naming them and why
    (:func:`baselines.reading.pipeline.nothing_line`)."""
    lines = (pipeline.nothing_line(r["reader"], r["budget"], r.get("read_nothing") or []) for r in rows)
    return [line for line in lines if line]


def cells_words(slides: list[dict], level: int) -> str:
    """What the cells are, for the printout and ``readers.json``: ``"bundle level 2 (downsample 4, about 4 × 4
    finest views a cell)"``, the same words as the budget curve's (:func:`baselines.reading.budget_curve`)."""
    ds = slides[0]["downsample"].get(level) if slides else None
    if not ds:
        return f"bundle level {level}"
    return f"bundle level {level} (downsample {ds:.3g}, about {ds:.3g} × {ds:.3g} finest views a cell)"


def load_split(dataset, head_path, split: str, cell_level: int | None = None, fold: int | None = None) -> tuple:
    """``(head, cell_level, slides)`` of :func:`baselines.reading.pipeline.load_split` with a head (the one loader):
    the slide head loaded from ``head_path`` and ``split``'s slides of ``dataset`` with the finest level and the
    cells of bundle level ``cell_level`` (default :func:`~baselines.reading.pipeline.cell_level_for`). Raises
    ``HistojaxDataError`` / ``ValueError`` naming the file."""
    split = pipeline.load_split(dataset, split, fold=fold, head=head_path, cell_level=cell_level, progress=True)
    return split.head, split.cell_level, split.slides


def print_tables(rows: list[dict], lesions: list[dict], budget: float = 0.1) -> None:
    """The curve as a markdown table, then the lesion table at ``budget`` (and reading everything)."""
    print(
        "| reader | budget | read (mean, p10–p90) | AUC [95 % interval] | AUC without ITC-only | accuracy |\n"
        "|---|---|---|---|---|---|"
    )
    for r in rows:
        every, kept = (
            format_auc_runs(r[k], r[f"{k}_std"], r[f"{k}_low"], r[f"{k}_high"], r["seeds"])
            for k in ("auc", "auc_no_itc")
        )
        print(
            f"| {r['reader']} | {r['budget']:.2f} | {r['fraction_read']:.3f} ({r['fraction_p10']:.3f}–"
            f"{r['fraction_p90']:.3f}) | {every} | {kept} | {r['accuracy']:.3f} |"
        )
    print(
        f"\nper lesion class: slides; read tumour / found by the head (above every normal slide), budget {budget:.2f}"
    )
    print("| reader | " + " | ".join(CLASSES) + " |\n|---|" + "---|" * len(CLASSES))
    for r in rows:
        if abs(r["budget"] - budget) < 1e-9 or r["kind"] in ("overview", "everything"):
            print(
                f"| {r['reader']} ({r['budget']:.2f}) | "
                + " | ".join(
                    f"{r[c + '_slides']}: {r[c + '_tumour_read']:.1f} / {r[c + '_found']:.1f}" for c in CLASSES
                )
                + " |"
            )
