"""The budget-curve plot labels a learned reader's point once where several budgets read the same
(a reader that declares at the overview reads 0 % at every budget: one label, not four on top of each other)."""

from __future__ import annotations

from baselines.reading.plots import coincident_points, plot_readers


def test_coincident_points_are_merged_with_their_budgets():
    x, y, b = [0.0, 0.0, 0.0, 0.12], [0.5, 0.5, 0.5, 0.7], [0.05, 0.1, 0.2, 0.5]
    assert coincident_points(x, y, b) == [(0.0, 0.5, [0.05, 0.1, 0.2]), (0.12, 0.7, [0.5])]
    assert len(coincident_points([0.05, 0.1], [0.6, 0.6], [0.05, 0.1])) == 2  # different fractions stay apart


def test_plot_writes_one_label_per_spot(tmp_path, monkeypatch):
    import matplotlib.axes

    texts = []
    real = matplotlib.axes.Axes.annotate
    monkeypatch.setattr(
        matplotlib.axes.Axes, "annotate", lambda self, text, *a, **k: (texts.append(text), real(self, text, *a, **k))[1]
    )
    rows = [
        {
            "reader": "overview only",
            "kind": "overview",
            "budget": 0.0,
            "fraction_read": 0.0,
            "auc": 0.56,
            "auc_std": 0.0,
            "auc_no_itc": 0.57,
            "auc_no_itc_std": 0.0,
        },
        {
            "reader": "read everything",
            "kind": "everything",
            "budget": 1.0,
            "fraction_read": 1.0,
            "auc": 0.84,
            "auc_std": 0.0,
            "auc_no_itc": 0.9,
            "auc_no_itc_std": 0.0,
        },
    ]
    rows += [
        {
            "reader": "lazy",
            "kind": "learned",
            "budget": b,
            "fraction_read": 0.0,
            "auc": 0.5,
            "auc_std": 0.0,
            "auc_no_itc": 0.5,
            "auc_no_itc_std": 0.0,
        }
        for b in (0.05, 0.1, 0.2, 0.5)
    ]
    out = plot_readers(rows, tmp_path / "readers.png", "t")
    assert out.exists()
    learned = [t for t in texts if "read" in t and "budget" in t]
    assert learned == ["budget 5%/10%/20%/50%: 0.0% read"] * 2  # once per panel (all slides, ITC left out)
