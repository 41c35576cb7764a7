"""The plots of the reading baselines: the budget curve's AUC / accuracy against the fraction read
(:func:`plot_curve`, rows of :mod:`baselines.reading.budget_curve`) and the readers' AUC with and without ITC-only
slides (:func:`plot_readers`, rows of :mod:`baselines.reading.readers` and the navigators' diagnosis)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from baselines import outputs


def method_kind(method: str) -> str:
    """The reader kind of a row's method: ``everything``, ``random``, ``scripted`` (attention / logit readers)
    or ``learned`` (a trained policy, its own diagnosis or a head on what it read)."""
    n = method.lower()
    if "read everything" in n:
        return "everything"
    if n.startswith("random reader"):
        return "random"
    if n.startswith(("attention reader", "logit reader")):
        return "scripted"
    return "learned"


CURVE_FAMILIES = {
    "everything": ["#1f4e9c", "#5d8fd6"],
    "random": ["#5f6a6a", "#a6acaf"],
    "scripted": ["#1e8449", "#58d68d", "#0e6251"],
    "learned": ["#c0392b", "#e67e22", "#8e44ad", "#d35400", "#e84393", "#a04000", "#f1948a", "#6c3483"],
}


def plot_curve(rows: list[dict], path, title: str = "") -> Path:
    """AUC and accuracy against the fraction actually read: one colour family per reader kind (blues: read
    everything, dashed; greys: random reader with a ± band over reading orders; greens: scripted readers;
    warm colours: trained policies, each drawn at the fraction it actually read, labelled, with a ± band over
    seeds); line style per head (solid: MIL, dashed: max logit, dotted: the policy's own diagnosis). A
    policy that reads nothing is one marked point at 0, not four piled up."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    methods = list(dict.fromkeys(r["method"] for r in rows))
    fig = Figure(figsize=(11.5, 7.0), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 1, sharex=True)
    for ax, metric in zip(axes, ("auc", "accuracy")):
        used: dict = {}
        zero: dict = {}  # trained readers that read nothing, grouped by their score (drawn once per score)
        for name in methods:
            kind = method_kind(name)
            family = CURVE_FAMILIES[kind]
            colour = family[used.get(kind, 0) % len(family)]
            used[kind] = used.get(kind, 0) + 1
            style = (
                "--"
                if ("max logit" in name or "max view logit" in name)
                else (":" if kind == "learned" and " + " not in name else "-")
            )
            mine = sorted((r for r in rows if r["method"] == name), key=lambda r: (r["fraction_read"], r["budget"]))
            x = np.asarray([r["fraction_read"] for r in mine])
            y = np.asarray([r[metric] for r in mine])
            e = np.nan_to_num(np.asarray([r.get(f"{metric}_std", 0.0) for r in mine], np.float64))
            if kind == "everything":
                ax.axhline(y[0], color=colour, linestyle=style, linewidth=1.3, label=f"{name} ({y[0]:.3f})")
                continue
            if kind == "learned" and (x < 1e-6).all():  # declares at the overview: one point at 0
                zero.setdefault(round(float(y.mean()), 3), []).append((name, float(e.mean()), colour))
                continue
            ax.plot(
                x,
                y,
                ("s" if kind == "learned" else "o"),
                linestyle=style,
                color=colour,
                linewidth=1.6,
                markersize=4.5,
                label=name,
            )
            if (e > 0).any():
                ax.fill_between(x, y - e, y + e, color=colour, alpha=0.15, linewidth=0)
            if kind == "learned" and metric == "auc":
                ax.annotate(
                    f"{name}: {x[-1]:.1%} read",
                    (x[-1], y[-1]),
                    textcoords="offset points",
                    xytext=(6, 4),
                    fontsize="x-small",
                    color=colour,
                )
        for k, (y0, group) in enumerate(sorted(zero.items())):
            name, err, colour = group[0]
            text = f"{name}: reads 0 %" if len(group) == 1 else f"{len(group)} rows reading 0 % ({y0:.3f})"
            ax.errorbar(
                [0.0],
                [y0],
                yerr=[err],
                fmt="*",
                markersize=12,
                color=colour,
                capsize=3,
                label=name + (f" and {len(group) - 1} more" if len(group) > 1 else "") + " (reads 0 %)",
            )
            ax.annotate(
                text,
                (0.0, y0),
                textcoords="offset points",
                xytext=(8, 4 - 10 * (k % 2)),
                fontsize="x-small",
                color=colour,
            )
        ax.set_xlim(-0.02, 1.02)
        ax.set_ylabel(metric.upper() if metric == "auc" else metric)
        low = min([r[metric] - (r.get(f"{metric}_std") or 0.0) for r in rows if r[metric] == r[metric]] + [0.5])
        ax.set_ylim(max(0.0, low - 0.05), 1.02)
        ax.grid(True, color="#dddddd", linewidth=0.6)
    axes[0].legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="small", frameon=False)
    axes[-1].set_xlabel("fraction of finest-level tissue views actually read (mean per episode)")
    axes[-1].set_xticks([0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 1.0], ["0", "10 %", "20 %", "30 %", "40 %", "50 %", "100 %"])
    if title:
        fig.suptitle(title, fontsize="medium")
    return outputs.save_figure(fig, path)


READER_FAMILIES = {
    "overview": ["#000000"],
    "random": ["#7f8c8d"],
    "scripted": ["#1e8449", "#58d68d", "#0e6251"],
    "learned": ["#c0392b", "#e67e22", "#8e44ad", "#d35400", "#e84393"],
    "everything": ["#1f4e9c"],
}


def coincident_points(x, y, budgets, places: int = 3) -> list[tuple[float, float, list[float]]]:
    """Points ``(x, y)`` merged where they coincide to ``places`` decimals (a reader that reads the same at
    several budgets): ``[(x, y, [budgets...])]`` in first-seen order, so each spot is labelled once."""
    out: dict[tuple, list] = {}
    for xi, yi, b in zip(x, y, budgets):
        out.setdefault((round(float(xi), places), round(float(yi), places)), [float(xi), float(yi), []])[2].append(
            float(b)
        )
    return [tuple(v) for v in out.values()]


def plot_readers(rows: list[dict], path, title: str = "") -> Path:
    """AUC against the fraction actually read, over all slides (left) and without ITC-only slides (right):
    one colour family per reader kind (grey: random, greens: scripted, warm colours: learned, each point
    drawn at the fraction it read and labelled), ± bands over seeds / reading orders, the overview-only
    point marked at 0, reading everything dashed."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(13.0, 5.2), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2, sharey=True)
    readers_ = list(dict.fromkeys(r["reader"] for r in rows))
    lo = min(min(r["auc"] - r["auc_std"], r["auc_no_itc"] - r["auc_no_itc_std"]) for r in rows)
    for ax, metric, label in zip(axes, ("auc", "auc_no_itc"), ("all slides", "ITC-only slides left out")):
        used = {}
        for name in readers_:
            mine = sorted((r for r in rows if r["reader"] == name), key=lambda r: r["fraction_read"])
            kind = mine[0]["kind"]
            family = READER_FAMILIES.get(kind, ["#444444"])
            colour = family[used.get(kind, 0) % len(family)]
            used[kind] = used.get(kind, 0) + 1
            x = np.asarray([r["fraction_read"] for r in mine])
            y = np.asarray([r[metric] for r in mine])
            e = np.asarray([r[f"{metric}_std"] for r in mine])
            if kind == "everything":
                ax.axhline(y[0], color=colour, linestyle="--", linewidth=1.4, label=f"{name} ({y[0]:.3f})")
                continue
            if kind == "overview":
                ax.plot(
                    x,
                    y,
                    marker="*",
                    markersize=15,
                    color=colour,
                    linestyle="none",
                    label=f"{name} ({y[0]:.3f}, reads 0 %)",
                )
                ax.annotate("overview only", (x[0], y[0]), textcoords="offset points", xytext=(9, -4), fontsize="small")
                continue
            ax.plot(
                x,
                y,
                "s-" if kind == "learned" else "o-",
                color=colour,
                linewidth=1.8,
                markersize=5,
                label=name + (" (± std over orders)" if kind == "random" else ""),
            )
            if (e > 0).any():
                ax.fill_between(x, y - e, y + e, color=colour, alpha=0.2, linewidth=0)
            if kind == "learned":  # each point at the fraction it read, labelled by its budget(s) once
                for j, (xi, yi, budgets) in enumerate(coincident_points(x, y, [r["budget"] for r in mine])):
                    text = f"budget {'/'.join(f'{b:.0%}' for b in budgets)}: {xi:.1%} read"
                    ax.annotate(
                        text,
                        (xi, yi),
                        textcoords="offset points",
                        xytext=(5, 6 if j % 2 else -12),
                        fontsize="x-small",
                        color=colour,
                    )
        ax.set_xlim(-0.02, max([0.55] + [r["fraction_read"] + 0.03 for r in rows if r["kind"] != "everything"]))
        ax.set_ylim(max(0.0, min(0.5, lo - 0.05)), 1.01)
        ax.set_xlabel("fraction of finest-level tissue views actually read (mean per episode)")
        ax.set_title(label, fontsize="medium")
        ax.grid(True, color="#dddddd", linewidth=0.6)
    axes[0].set_ylabel("slide AUC (same head for every reader)")
    axes[1].legend(loc="lower right", fontsize="small", framealpha=0.9)
    if title:
        fig.suptitle(title, fontsize="medium")
    return outputs.save_figure(fig, path)
