"""Scripted readers, CAMELYON lesion classes and the budget curve with one slide head for every row:
``python -m baselines.reading.readers --dataset DIR --head DIR --out DIR``.

The readers are the reading pipeline (:mod:`baselines.reading.pipeline`: one loader of a split's slides, one run
loop over readers × budgets) on the cells of a bundle level; the budget curve (:mod:`baselines.reading.budget_curve`)
is the same pipeline on the env's glimpse cells. Every reader produces, per slide and budget, a **read mask**
``(H, W)`` bool over the finest-level views; the same head (:mod:`histojax.reading.heads.logit`, fitted by :mod:`baselines.reading.head_fit`) scores every mask:

* ``overview only`` — nothing of the finest level is read (fraction 0): the head applied to the cell
  grid's own low-resolution logits (the overview every reader sees before reading);
* ``random reader`` — cells in a uniformly random order (``--seeds`` orders, mean ± std);
* ``logit reader`` — cells by their low-resolution tumour logit, highest first (follow the coarse logits);
  with a head that reads every feature entry (the learned attention-MIL head, any encoder) this row is the
  ``score reader``: cells by the head's per-view score (:meth:`view_logits`) of the cell's coarse feature
  vector, highest first (the logit reader is the score reader of a logit head: its per-view score is entry
  ``dim``);
* ``search reader`` — the logit (score) reader, except that once a read cell shows a finest view score above
  ``SEARCH_THRESHOLD`` its unread neighbouring cells are read next (hottest first): a spatial search
  around the best cells;
* ``read everything`` — every tissue view (fraction 1);
* learned readers — any reader's masks, added with :func:`baselines.reading.reader_scores.add_reader` (e.g. from
  :func:`baselines.reading.pipeline.policy_reads` through :func:`baselines.reading.reader_scores.masks_from_instances`).

**Cells** are the views of bundle level ``--cell-level`` (default: the level whose downsample is nearest 4,
so that a cell covers about 4 × 4 finest views; on the C16 sets, level 3, ×3.67); a cell is valid when a finest tissue view lies under
it. A reader reads cells as the ``glimpse`` env does (:func:`baselines.reading.orders.read_cells`): a cell
is read while its tissue views still fit in ``floor(budget · tissue views)``; the first pick that does
not fit ends the reading. Fractions are of the slide's finest-level tissue views.

**Lesion classes** (CAMELYON's rule on the largest lesion's longest diameter, from the bundle's tumour
polygons at the bundle's µm/px): ``ITC`` < 0.2 mm, ``micro`` 0.2–2 mm, ``macro`` > 2 mm. AUC is
reported over all test slides and over normal vs micro/macro (ITC-only slides left out). A reader
*reads tumour* on a slide when a view it read overlaps the tumour; the head *finds* a slide when it
scores it above every normal test slide.

Every AUC is :func:`baselines.reading.pipeline.reader_auc` (mean ± std over seeds, ``auc_low`` / ``auc_high`` its 95 %
interval over the slides), the one the budget curve's ``--head`` rows use too; the cells read are printed.
Writes ``readers.csv`` (one row per reader × budget), ``lesions.csv`` (per test tumour slide),
``readers.json``, ``readers.png`` and, per trained reader, reading maps ``reading_<reader>_tumour.png`` /
``_normal.png`` (:func:`reading_map`: the head's per-view scores beside the views the reader read, at the budget
nearest 10 %).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from baselines import outputs
from baselines.reading import pipeline
from baselines.reading.csv_files import write_csv
from baselines.reading.pipeline import BUDGETS
from baselines.reading.plots import plot_readers
from baselines.reading.provenance import (
    add_flag,
    check_policy,
    check_scored,
    head_for_fold,
    mark_words,
    seen_mark,
    with_seen,
)
from baselines.reading.reader_scores import (
    add_reader,
    cells_words,
    csv_rows,
    load_split,
    nothing_lines,
    policy_masks,
    print_tables,
    rows_from_results,
    scripted_results,
    tumour_views,
)
from baselines.reading.slides import HeadDataError, lesion_class
from data_tools.cli_output import command_main, print_error
from data_tools.errors import HistojaxDataError
from data_tools.metrics import json_safe, small_split_warning
from histojax import compile_cache
from histojax.reading.heads import same_encoder


# ----------------------------------------------------------------------------- lesions
def lesion_rows(slides: list[dict], results: dict | None = None, head=None) -> list[dict]:
    """Per tumour slide: lesion class, largest lesion's longest diameter (mm), tumour area (mm²), tumour
    views, and the read-everything head logit (when ``results`` holds it)."""
    every = (results or {}).get(("read everything", 1.0))
    labels = np.asarray([s["label"] for s in slides])
    top_normal = float(every["scores"][0][labels == 0].max()) if every is not None and (labels == 0).any() else None
    out = []
    for i, s in enumerate(slides):
        if not s["label"]:
            continue
        cls, mm = lesion_class(s)
        area = float(s["tumour"].area) * s["mpp"] ** 2 / 1e6 if s.get("tumour") is not None else float("nan")
        row = {
            "slide": s["name"],
            "class": cls,
            "diameter_mm": mm,
            "area_mm2": area,
            "tumour_views": int(tumour_views(s).sum()),
        }
        if every is not None:
            row["head_logit"] = float(every["scores"][0][i])
            row["above_every_normal"] = bool(top_normal is None or row["head_logit"] > top_normal)
        out.append(row)
    return sorted(out, key=lambda r: r["diameter_mm"])


# ----------------------------------------------------------------------------- output
def reading_map(slide: dict, mask: np.ndarray, path, reader: str = "", head_name: str = "", budget=None) -> Path:
    """A PNG of where a reader read on one slide, beside what the head sees: left the head's per-view scores of
    the finest tissue views (``slide["logits"]``: a learned head's calibrated instance logits, a logit head's view
    logit), right the views read (``mask (H, W)`` bool) over the tissue; tumour views (from the annotation, when
    the slide has one) outlined on both. Returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    tissue = slide["tissue"]
    scores = np.where(tissue, slide["logits"], np.nan)
    tumour = tumour_views(slide)
    mask = np.asarray(mask, bool) & tissue
    h, w = tissue.shape
    fig = Figure(figsize=(11.0, 4.6 * h / max(w, 1) + 1.2), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    left, right = fig.subplots(1, 2)
    im = left.imshow(scores, cmap="magma", interpolation="nearest")
    fig.colorbar(im, ax=left, fraction=0.04, label="head's per-view score (logit)")
    left.set_title(f"per-view scores of {head_name or 'the head'}", fontsize="small")
    shown = np.where(tissue, 0.25, 0.0) + np.where(mask, 0.75, 0.0)
    right.imshow(shown, cmap="Blues", vmin=0, vmax=1, interpolation="nearest")
    fraction = mask.sum() / max(1, tissue.sum())
    right.set_title(
        f"{reader or 'reader'}: {mask.sum()} views read ({fraction:.1%} of tissue"
        + (f", budget {budget:.0%}" if budget is not None else "")
        + ")",
        fontsize="small",
    )
    for ax in (left, right):
        if tumour.any():
            ax.contour(tumour.astype(float), levels=[0.5], colors="#2ecc71", linewidths=1.2)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(
        f"{slide['name']}: {'tumour' if slide['label'] else 'normal'} slide"
        + (" (green: tumour views)" if tumour.any() else ""),
        fontsize="medium",
    )
    return outputs.save_figure(fig, path)


def write_reading_maps(
    out: Path, slides: list[dict], name: str, masks: list[np.ndarray], head_name: str, budget: float
) -> list[Path]:
    """:func:`reading_map` of a reader's masks on the first tumour and the first normal slide:
    ``out/reading_<reader>_tumour.png`` / ``_normal.png``."""
    safe = "".join(c if c.isalnum() else "-" for c in name).strip("-") or "reader"
    written = []
    for label, word in ((1, "tumour"), (0, "normal")):
        i = next((k for k, s in enumerate(slides) if s["label"] == label), None)
        if i is not None:
            written.append(
                reading_map(slides[i], masks[i], out / f"reading_{safe}_{word}.png", name, head_name, budget)
            )
    return written


def add_arguments(p) -> None:
    """The options of ``python -m baselines.reading.readers``."""
    from baselines.published_agents import published_or_path

    p.add_argument("--dataset", required=True, help="dataset folder (dataset.json; feature grids of any encoder)")
    p.add_argument(
        "--head",
        required=True,
        type=published_or_path,
        help="slide head folder (python -m baselines.reading.head_fit) or a published head's name",
    )
    p.add_argument("--split", default="test", help="split scored (default test)")
    p.add_argument(
        "--fold",
        type=int,
        default=None,
        metavar="I",
        help="a dataset built with --folds K: score fold I's side of --split (test / validation = fold I)",
    )
    p.add_argument(
        "--budgets", type=float, nargs="+", default=list(BUDGETS), help="fractions read (default 5/10/20/50 %%)"
    )
    p.add_argument("--seeds", type=int, default=5, help="random reader orders (default 5)")
    p.add_argument(
        "--cell-level",
        type=int,
        default=None,
        help="bundle level of the cells (default: the level whose downsample is nearest 4, so that a cell "
        "covers about 4 × 4 finest views)",
    )
    p.add_argument(
        "--reader",
        nargs=2,
        action="append",
        default=[],
        metavar=("NAME", "RUN"),
        help="also a trained reader (run folder of `python -m baselines.ppo` or `baselines.ppo_rnn` in a "
        "glimpse or zoom_select mode): the head on what it reads at each budget",
    )
    p.add_argument("--policy-seeds", type=int, default=3, help="seeds of each --reader run (default 3, or fewer)")
    p.add_argument("--out", default="runs/readers", help="output folder (default runs/readers)")
    add_flag(p)


def run(args, parser=None) -> int:
    """Score every reader at every budget; CSV, JSON, PNG in ``args.out``."""
    if not all(0.0 < b <= 1.0 for b in args.budgets):
        return print_error(f"--budgets must lie in (0, 1], got {args.budgets}")
    if args.seeds < 1 or (args.cell_level is not None and args.cell_level < 1):
        return print_error("--seeds and --cell-level must be ≥ 1")
    t0 = time.perf_counter()
    try:
        from histojax.reading import heads

        if args.fold is not None:  # the folder of learned_head_fit --all-folds (or DIR{fold}): fold I's head
            args.head = head_for_fold(args.head, args.fold)
        head = heads.load(args.head)  # a head fitted on the scored slides: refused before they are read
        scored = pipeline.read_spec(args.dataset, args.fold).get(args.split) or []
        allow = getattr(args, "allow_fitting_slides", False)
        check_scored(head, args.head, args.dataset, scored, allow)
        mark = seen_mark(head, args.dataset, scored)
        for name, run_dir in args.reader:  # a trained reader's own slides: refused too, before any is read
            names = check_policy(run_dir, args.dataset, scored, allow, option=f"--reader {name}")
            mark = with_seen(mark, f"policy {name}", names)
        head, args.cell_level, slides = load_split(args.dataset, head, args.split, args.cell_level, args.fold)
    except (HistojaxDataError, ValueError) as e:
        return print_error(e)
    other = sorted({str(s["encoder"]) for s in slides if head.encoder and not same_encoder(head.encoder, s["encoder"])})
    if other:
        return print_error(
            f"{args.head}: a head for {head.encoder} features; {args.dataset} holds {', '.join(other)} "
            "features (fit a head on it: python -m baselines.reading.head_fit)"
        )
    problem = pipeline.one_class_problem(args.split, [s["label"] for s in slides], args.fold)
    if problem:
        return print_error(HeadDataError(Path(args.dataset) / "dataset.json", problem))
    cells = cells_words(slides, args.cell_level)
    results = scripted_results(head, slides, args.budgets, args.seeds, args.cell_level, progress=True)
    maps = {}
    for name, run_dir in args.reader:
        why = {}
        try:
            masks = policy_masks(
                run_dir, args.dataset, slides, args.split, args.budgets, args.policy_seeds, fold=args.fold, why=why
            )
        except (OSError, ValueError, HistojaxDataError) as e:
            return print_error(f"--reader {name}: {e}")
        add_reader(results, head, slides, name, masks, "learned", nothing=why)
        maps[name] = masks
    rows = rows_from_results(results, slides)
    lesions = lesion_rows(slides, results)
    warning = small_split_warning(
        int(sum(s["label"] for s in slides)),
        int(sum(1 - s["label"] for s in slides)),
        pipeline.split_words(args.dataset, args.split, args.fold),
    )
    if warning:  # once scored: a refusal above stays one line
        print(warning, file=sys.stderr)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    b = min(args.budgets, key=lambda v: abs(v - 0.1))  # reading maps at the budget nearest 10 %
    for name, masks in maps.items():  # a trained reader's first seed: where it read beside the head's scores
        write_reading_maps(out, slides, name, masks[float(b)][0], head.name, b)
    seen = {"scored_on_seen_slides": mark_words(mark)} if mark else {}  # --allow-fitting-slides: marked
    write_csv([{**r, **seen} for r in csv_rows(rows)], out / "readers.csv")
    write_csv(lesions, out / "lesions.csv")
    wall = time.perf_counter() - t0
    outputs.write_text(
        out / "readers.json",
        json.dumps(
            json_safe(
                {
                    "dataset": str(args.dataset),
                    "split": args.split,
                    **({"fold": args.fold} if args.fold is not None else {}),
                    "head": str(args.head),
                    "head_name": head.name,
                    **mark,  # self_scored, scored_on_seen_slides: slides the head or a reader saw (--allow-fitting-slides)
                    "cell_level": args.cell_level,
                    "cells": cells,
                    "seeds": args.seeds,
                    "wall_s": round(wall, 1),
                    "rows": rows,
                    "lesions": lesions,
                }
            ),
            indent=1,
            allow_nan=False,
        ),
    )
    png = plot_readers(
        rows,
        out / "readers.png",
        f"{Path(args.dataset).name}, {pipeline.split_words(args.dataset, args.split, args.fold)} ({len(slides)} "
        f"slides): head {head.name}",
    )
    print(f"cells: {cells}")
    print_tables(rows, lesions)
    for line in nothing_lines(rows):  # a row that read nothing on some slides: which, and why
        print(f"warning: {line}")
    print(f"wrote {out}/readers.csv, lesions.csv, readers.json and {png} in {wall:.0f} s")
    return 0


main = command_main(add_arguments, run, "python -m baselines.reading.readers", __doc__)


if __name__ == "__main__":
    raise SystemExit(main(compile_cache.setup(sys.argv[1:])))  # the persistent compilation cache, --no-compile-cache
