"""The 95 % intervals over slides of the C16 results pages' headline AUCs (docs/results/c16.md, readers.md,
learned-head.md, diagnosis.md), from each figure as the page prints it and the class counts of the split it was
measured on (:func:`data_tools.metrics.auc_interval`, Newcombe's score interval). No figure is measured again: the
pages' figures are copied here as they are printed, and each interval is the one an AUC of that value has on that
many tumour and normal slides.

    python -m experiments.results_intervals                # every page's table of intervals (Markdown)
    python -m experiments.results_intervals --page readers  # one page's
    python -m experiments.results_intervals 0.865 25 34    # one AUC on 25 tumour and 34 normal slides

A figure given as mean ± std over seeds (or reading orders) gets the interval of the mean's AUC on the split's counts:
the spread over slides of one AUC of that value, not an interval of the mean over seeds.
"""

from __future__ import annotations

import argparse
import sys

from data_tools.metrics import auc_interval

#: (tumour, normal) slides of the splits the C16 pages score: the 59 test slides of ``c16-full`` (25 tumour, 34
#: normal; 23 tumour once its 2 ITC-only slides are left out), the 35 validation slides the v1 agents and the heads
#: were chosen on (15 tumour, 20 normal) and the 52 the v2 readers were chosen on (22 tumour, 30 normal).
SPLITS = {
    "test": (25, 34),
    "test w/o ITC": (23, 34),
    "validation (35)": (15, 20),
    "validation (52)": (22, 30),
}

#: page -> [(row, figure as printed, split)]: the headline AUCs of each page, copied as printed.
HEADLINES = {
    "c16": [
        ("v1 reference, PPO, Diagnosis AUC (3 seeds)", "0.597 ± 0.048", "test"),
        ("v1 reference, recurrent PPO (GRU), Diagnosis AUC (3 seeds)", "0.528 ± 0.032", "test"),
        ("v1 reference, PPO, validation, best seed", "0.739", "validation (35)"),
        ("v1 reference, recurrent PPO, validation, best seed", "0.712", "validation (35)"),
        ("budget curve: max of pcam-cnn's view logit, read everything", "0.865", "test"),
        ("budget curve: random reader + max logit at 10 % (5 orders)", "0.749 ± 0.045", "test"),
        ("budget curve: logit reader + max logit at 10 %", "0.713", "test"),
        ("budget curve: gated-attention MIL, read everything", "0.769", "test"),
        ("budget curve: random reader + MIL at 10 % (5 orders)", "0.617 ± 0.039", "test"),
        ("budget curve: attention reader + MIL at 10 %", "0.671", "test"),
        ("budget curve: PPO `zoom_select` at 10 %, own diagnosis (3 seeds)", "0.687 ± 0.023", "test"),
        ("budget curve: PPO `glimpse:1` at 10 %, own diagnosis (3 seeds)", "0.835 ± 0.008", "test"),
        ("budget curve: recurrent PPO `glimpse:1` at 10 %, greedy (3 seeds)", "0.788 ± 0.011", "test"),
        ("published `c16-v1-diagnosis`", "0.657", "test"),
        ("published `c16-v2-set-reader` (greedy, `histojax evaluate`)", "0.775", "test"),
        ("`c16-v2-set-reader`'s run, 3 seeds", "0.793 ± 0.032", "test"),
        ("published `c16-v2-head`, read everything", "0.838", "test"),
        ("published `c16-v2-head`, read everything, ITC-only left out", "0.895", "test w/o ITC"),
        ("published `c16-v2-head-mil`, read everything", "0.859", "test"),
        ("published `c16-v2-head-mil`, read everything, ITC-only left out", "0.912", "test w/o ITC"),
        ("published `c16-v2-head-navigator`", "0.404", "test"),
        ("published `c16-v1-zoom-reader` (its 3 seeds)", "0.687 ± 0.023", "test"),
        ("published `c16-v1-diagnosis`, validation", "0.739", "validation (35)"),
        ("published `c16-v2-set-reader`, validation at 10 %", "0.761", "validation (52)"),
        ("published `c16-v2-head-navigator`, validation", "0.714", "validation (52)"),
    ],
    "readers": [
        ("overview only", "0.568", "test"),
        ("overview only, ITC-only left out", "0.569", "test w/o ITC"),
        ("random reader at 10 % (5 orders)", "0.721 ± 0.048", "test"),
        ("random reader at 10 %, ITC-only left out", "0.752 ± 0.047", "test w/o ITC"),
        ("logit reader at 10 %", "0.864", "test"),
        ("logit reader at 10 %, ITC-only left out", "0.902", "test w/o ITC"),
        ("search reader at 10 %", "0.671", "test"),
        ("search reader at 10 %, ITC-only left out", "0.685", "test w/o ITC"),
        ("random reader at 50 % (5 orders)", "0.830 ± 0.028", "test"),
        ("logit reader at 50 %", "0.772", "test"),
        ("read everything", "0.838", "test"),
        ("read everything, ITC-only left out", "0.895", "test w/o ITC"),
        ("set reader at 5 % (3 seeds)", "0.741 ± 0.017", "test"),
        ("set reader at 10 % (3 seeds)", "0.793 ± 0.032", "test"),
        ("set reader at 10 %, ITC-only left out", "0.841 ± 0.032", "test w/o ITC"),
        ("set reader at 20 % (3 seeds)", "0.843 ± 0.024", "test"),
        ("set reader at 50 % (3 seeds)", "0.800 ± 0.021", "test"),
        ("set reader at 10 %, validation, 1 M steps (3 seeds)", "0.735 ± 0.024", "validation (52)"),
        ("set reader at 10 %, validation, 4 M steps (3 seeds)", "0.717 ± 0.007", "validation (52)"),
        ("set reader at 10 %, test, 4 M steps (3 seeds)", "0.768 ± 0.021", "test"),
    ],
    "learned-head": [
        ("learned head, read everything (3 fits)", "0.831 ± 0.014", "test"),
        ("learned head, read everything, ITC-only left out (3 fits)", "0.889 ± 0.015", "test w/o ITC"),
        ("learned head under a random rotation (3 fits)", "0.834 ± 0.009", "test"),
        ("learned head under a random rotation, ITC-only left out (3 fits)", "0.884 ± 0.012", "test w/o ITC"),
        ("published `c16-v2-learned-head` (seed 0)", "0.849", "test"),
        ("published `c16-v2-learned-head`, ITC-only left out", "0.907", "test w/o ITC"),
        ("learned head, validation (3 fits)", "0.974 ± 0.020", "validation (35)"),
        ("through the learned head: overview only", "0.702", "test"),
        ("random reader at 10 % (5 orders)", "0.728 ± 0.059", "test"),
        ("score reader at 10 %", "0.829", "test"),
        ("search reader at 10 %", "0.819", "test"),
        ("set reader at 10 %, 1 M steps (3 seeds)", "0.811 ± 0.009", "test"),
        ("set reader at 10 %, 5 M steps (3 seeds)", "0.800 ± 0.014", "test"),
        ("published `c16-v2-learned-set-reader` (greedy, `histojax evaluate`)", "0.819", "test"),
        ("published `c16-v2-learned-set-reader`, ITC-only left out", "0.867", "test w/o ITC"),
        ("set reader at 10 %, validation, 1 M steps (3 seeds)", "0.851 ± 0.091", "validation (52)"),
    ],
    "diagnosis": [
        ("MIL on colour-stats, read everything", "0.798", "test"),
        ("random reader + MIL at 10 %", "0.598", "test"),
        ("attention reader + MIL at 10 %", "0.686", "test"),
        ("random reader + MIL at 20 %", "0.708", "test"),
        ("attention reader + MIL at 20 %", "0.764", "test"),
        ("random reader + MIL at 50 %", "0.792", "test"),
        ("attention reader + MIL at 50 %", "0.787", "test"),
    ],
}


def figure_mean(text: str) -> float:
    """The AUC of a figure as a page prints it: ``"0.793 ± 0.032"`` (mean ± std over seeds) -> 0.793."""
    return float(text.split("±")[0])


def interval_text(auc: float, n_tumour: int, n_normal: int) -> str:
    """``"[0.741, 0.936]"``: :func:`data_tools.metrics.auc_interval` of ``auc`` on these counts, to 3 decimals."""
    low, high = auc_interval(auc, n_tumour, n_normal)
    return f"[{low:.3f}, {high:.3f}]"


def page_table(page: str) -> str:
    """One page's headline AUCs with their 95 % intervals, a Markdown table."""
    lines = ["| figure | AUC as printed | 95 % interval over slides | slides (tumour / normal) |", "|---|---|---|---|"]
    for row, text, split in HEADLINES[page]:
        t, n = SPLITS[split]
        mean = " (of the mean)" if "±" in text else ""
        lines.append(f"| {row} | {text} | {interval_text(figure_mean(text), t, n)}{mean} | {split}: {t} / {n} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m experiments.results_intervals",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("figure", nargs="*", help="AUC N_TUMOUR N_NORMAL: one interval")
    p.add_argument("--page", choices=sorted(HEADLINES), default=None, help="one page's table (default: every page)")
    args = p.parse_args(argv)
    if args.figure:
        if len(args.figure) != 3:
            p.error("give AUC N_TUMOUR N_NORMAL (e.g. 0.865 25 34)")
        auc, t, n = float(args.figure[0]), int(args.figure[1]), int(args.figure[2])
        print(f"AUC {auc:.3f} {interval_text(auc, t, n)} on {t} tumour and {n} normal slides")
        return 0
    for page in [args.page] if args.page else sorted(HEADLINES):
        print(f"## docs/results/{page}.md\n\n{page_table(page)}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
