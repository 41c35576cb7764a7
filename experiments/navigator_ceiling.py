"""The ceiling of a navigator's diagnosis through the slide head: what an episode of ``--max-steps`` steps
can read at most, and what the one-head readers reach at that fraction.

    python -m experiments.navigator_ceiling --dataset DIR --head HEAD [--split test] [--max-steps 200] \\
        [--budgets 0.005 0.01 0.02] [--seeds 5] [--out DIR]

A navigator stands on one view per step, so a ``--max-steps`` episode reads at most ``max_steps`` finest
tissue views of a slide (fewer: it also zooms and moves over views it has read). Prints, over the split's
slides, the finest tissue views per slide and the fraction ``max_steps / views`` (median, min, max), then the
head's AUC (all slides; ITC-only slides left out) for the readers of :mod:`baselines.reading.readers` (overview only,
random reader over ``--seeds`` orders, logit reader — a learned head's score reader —, search reader, read
everything) at ``--budgets``, and each reader at **each slide's own ceiling** (``max_steps`` views of that slide: the
row ``budget = median ceiling``). Writes ``OUT/readers.csv`` and ``OUT/ceiling.json``. ``--head``: any head folder
:func:`histojax.reading.heads.load` reads; the split is scored by the loop :mod:`baselines.reading.diagnosis` shares
(:func:`~baselines.reading.diagnosis.score_split`: a split of one class refused, its AUC undefined). A head fitted
or validated on a scored slide is refused, as by every scorer (``--allow-fitting-slides``: warned, and the files
written say on which).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

from baselines.reading import reader_scores
from baselines.reading.diagnosis import score_split, write_results
from baselines.reading.orders import logit_order, random_order, read_mask, search_order
from baselines.reading.provenance import add_flag, check_scored, seen_mark
from data_tools.cli_output import command_main, print_error
from data_tools.errors import HistojaxDataError
from data_tools.metrics import small_split_warning


def ceiling_fractions(slides: list[dict], max_steps: int) -> np.ndarray:
    """``(n,)`` float: per slide, the largest fraction of its finest tissue views that ``max_steps`` views
    make (``min(1, max_steps / tissue views)``)."""
    views = np.asarray([max(1, int(s["tissue"].sum())) for s in slides], np.float64)
    return np.minimum(1.0, max_steps / views)


def at_ceiling(head, slides: list[dict], results: dict, ceilings: np.ndarray, level: int, seeds: int) -> float:
    """Add the random (``seeds`` orders), logit (a learned head's: score) and search readers, each reading up to its
    slide's own ``ceilings[i]`` fraction, to ``results`` under the budget ``median(ceilings)``; returns that key."""
    key = float(np.median(ceilings))
    tables = [reader_scores.cell_table(s, level) for s in slides]
    tumour = [reader_scores.tumour_views(s) for s in slides]
    orders = {
        reader_scores.score_reader_name(head): [logit_order(c) for c in tables],
        "search reader": [search_order(s, c, limit=float(b) + 0.01) for s, c, b in zip(slides, tables, ceilings)],
    }
    for name, ords in orders.items():
        masks = [[read_mask(c, s["tissue"], o, float(b))[0] for s, c, o, b in zip(slides, tables, ords, ceilings)]]
        reader_scores.add_reader(results, head, slides, f"{name}, per-slide ceiling", {key: masks}, "scripted", tumour)
    masks = [
        [
            read_mask(c, s["tissue"], random_order(c, np.random.default_rng(1000 * k + i)), float(b))[0]
            for i, (s, c, b) in enumerate(zip(slides, tables, ceilings))
        ]
        for k in range(seeds)
    ]
    reader_scores.add_reader(results, head, slides, "random reader, per-slide ceiling", {key: masks}, "random", tumour)
    return key


def add_arguments(p) -> None:
    """The options of ``python -m experiments.navigator_ceiling``."""
    p.add_argument("--dataset", required=True, help="dataset folder (dataset.json; feature grids the head reads)")
    p.add_argument("--head", required=True, help="slide head folder (any kind histojax.reading.heads.load reads)")
    p.add_argument("--split", default="test", help="split scored (default test)")
    p.add_argument("--max-steps", type=int, default=200, help="steps per navigator episode (default 200)")
    p.add_argument("--budgets", type=float, nargs="+", default=[0.005, 0.01, 0.02], help="fractions read")
    p.add_argument("--seeds", type=int, default=5, help="random reader orders (default 5)")
    p.add_argument("--out", default="runs/navigator-ceiling", help="output folder")
    add_flag(p)


def run(args, parser=None) -> int:
    """Print the ceiling fractions and the readers' AUC at them; CSV and JSON in ``args.out``."""
    if args.max_steps < 1 or args.seeds < 1 or not all(0.0 < b <= 1.0 for b in args.budgets):
        return print_error("--max-steps and --seeds must be ≥ 1 and --budgets in (0, 1]")
    t0 = time.perf_counter()
    try:
        from baselines.reading.slides import read_spec
        from histojax.reading import heads

        scored = read_spec(args.dataset, None).get(args.split) or []
        check_scored(heads.load(args.head), args.head, args.dataset, scored, args.allow_fitting_slides)
        mark = seen_mark(heads.load(args.head), args.dataset, scored)  # the flag: the written files say so
        head, level, slides, results = score_split(args.dataset, args.head, args.split, args.budgets, args.seeds)
    except (HistojaxDataError, ValueError) as e:
        return print_error(e)
    ceilings = ceiling_fractions(slides, args.max_steps)
    views = np.asarray([int(s["tissue"].sum()) for s in slides])
    key = at_ceiling(head, slides, results, ceilings, level, args.seeds)
    out = Path(args.out)
    wall = time.perf_counter() - t0
    rows = write_results(
        out,
        results,
        slides,
        {
            "dataset": str(args.dataset),
            "split": args.split,
            "head": str(args.head),
            "max_steps": args.max_steps,
            "slides": len(slides),
            "tissue_views_median": float(np.median(views)),
            "tissue_views_min": int(views.min()),
            "tissue_views_max": int(views.max()),
            "ceiling_median": float(np.median(ceilings)),
            "ceiling_min": float(ceilings.min()),
            "ceiling_max": float(ceilings.max()),
            "ceiling_key": key,
            "wall_s": round(wall, 1),
        },
        "ceiling.json",
        mark=mark,
    )
    print(
        f"{len(slides)} slides: finest tissue views median {np.median(views):.0f} (min {views.min()}, max "
        f"{views.max()}); {args.max_steps} views = {100 * np.median(ceilings):.3f} % of a slide's finest tissue "
        f"(median; min {100 * ceilings.min():.3f} %, max {100 * ceilings.max():.3f} %)"
    )
    reader_scores.print_tables(rows, [])
    labels = [int(s["label"]) for s in slides]
    if (warning := small_split_warning(sum(labels), len(labels) - sum(labels), f"split {args.split!r}")) is not None:
        print(warning, file=sys.stderr)
    print(f"wrote {out}/readers.csv and ceiling.json in {wall:.0f} s")
    return 0


main = command_main(add_arguments, run, "python -m experiments.navigator_ceiling", __doc__)


if __name__ == "__main__":
    raise SystemExit(main())
