"""The dataset's default train / test split keeps every patient on one side (the label table's patient column, else
the TCGA barcode's patient), as the folds do; a slide listed with two patients is refused; a given split that puts
one patient on both sides is warned about; dataset.json records how the split was grouped. Pure planning: no slide
is read."""

from __future__ import annotations

import warnings
from pathlib import Path
from types import SimpleNamespace

import pytest

from data_tools.datasets.build import make_plan
from data_tools.datasets.split import patients_on_both_sides, read_patient_column
from data_tools.errors import HistojaxDataError


def _entries(root: Path, rows):
    """Discovered-slide stand-ins: ``rows`` of ``(name, label, split or None)``."""
    return [
        SimpleNamespace(
            name=n,
            label=lab,
            split=sp,
            path=root / f"{n}.svs",
            annotation=None,
            annotation_kind=None,
            label_source="table",
        )
        for n, lab, sp in rows
    ]


def _tcga_cohort(root):
    """20 TCGA slides: patients 0-3 have two slides each (a tumour and a normal one), the others one."""
    rows = []
    for p in range(14):
        rows.append((f"TCGA-AA-{p:04d}-01Z-00-DX1", p % 2, None))
        if p < 4:
            rows.append((f"TCGA-AA-{p:04d}-11Z-00-DX1", 1 - p % 2, None))
    return _entries(root, rows[:20])


@pytest.mark.parametrize("seed", range(8))
def test_the_default_split_keeps_each_tcga_patient_on_one_side(tmp_path, seed):
    plan = make_plan(_tcga_cohort(tmp_path), tmp_path, {}, 0.25, seed)
    side: dict[str, set] = {}
    for name, rec in plan["slides"].items():
        side.setdefault(name[:12], set()).add(rec["split"])
    assert all(len(s) == 1 for s in side.values()), side
    assert {"train", "test"} == {r["split"] for r in plan["slides"].values()}
    assert plan["split_grouped_by"] == "the TCGA barcode's patient (TCGA-XX-XXXX)"
    assert "one patient on one side" in plan["split_rule"]


def test_the_label_tables_patient_column_groups_the_split(tmp_path):
    rows = [(f"s{i:02d}", i % 2, None) for i in range(16)]
    table = tmp_path / "labels.csv"
    table.write_text("slide,label,patient\n" + "".join(f"{n},{lab},P{i // 4}\n" for i, (n, lab, _) in enumerate(rows)))
    patients = read_patient_column(table)
    for seed in range(4):
        plan = make_plan(_entries(tmp_path, rows), tmp_path, {}, 0.25, seed, patients=patients)
        for p in range(4):
            assert len({plan["slides"][f"s{i:02d}"]["split"] for i in range(4 * p, 4 * p + 4)}) == 1
        assert plan["split_grouped_by"] == "the label table's patient column"


def test_one_slide_per_patient_keeps_the_split_it_always_had(tmp_path):
    """Cohorts with no patient of two slides (CAMELYON16 names, a patient column of distinct patients) get the split
    and split rule of before: existing datasets resume and rebuild to the same split."""
    from data_tools.datasets.split import seeded_split

    rows = [(f"slide{i:02d}", int(i < 7), None) for i in range(20)]
    labels = {n: lab for n, lab, _ in rows}
    before = seeded_split([n for n, _, _ in rows], labels, 0.25, 3)
    plan = make_plan(
        _entries(tmp_path, rows), tmp_path, {}, 0.25, 3, patients={n: f"P{i}" for i, (n, _, _) in enumerate(rows)}
    )
    assert sorted(n for n, r in plan["slides"].items() if r["split"] == "test") == before[1]
    assert plan["split_rule"] == "seeded (seed 3), stratified by label, 25% of each label in test"


def test_a_slide_listed_with_two_patients_is_refused_in_one_line(tmp_path):
    table = tmp_path / "labels.csv"
    table.write_text("slide,label,patient\nA,1,P1\nB,0,P2\na.svs,1,P3\n")
    with pytest.raises(HistojaxDataError) as err:
        read_patient_column(table)
    line = str(err.value)
    assert "\n" not in line and str(table) in line and "'a'" in line and "two patients" in line
    table.write_text("slide,label,patient\nA,1,P1\nB,0,P2\nA,1,P1\n")  # the same patient twice: one slide, fine
    assert read_patient_column(table) == {"A": "P1", "B": "P2"}


def test_a_given_split_with_a_patient_on_both_sides_is_warned_naming_the_patient(tmp_path):
    rows = [
        ("TCGA-AA-0001-01Z-00-DX1", 1, "train"),
        ("TCGA-AA-0001-11Z-00-DX1", 0, "test"),
        ("TCGA-AA-0002-01Z-00-DX1", 1, "test"),
        ("TCGA-AA-0003-01Z-00-DX1", 0, "train"),
    ]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plan = make_plan(_entries(tmp_path, rows), tmp_path, {}, 0.25, 0)
    lines = [str(w.message) for w in caught]
    assert len(lines) == 1 and "TCGA-AA-0001" in lines[0] and "both sides" in lines[0], lines
    assert {n: r["split"] for n, r in plan["slides"].items()} == {n: s for n, _, s in rows}  # warned, not changed
    assert patients_on_both_sides({"x": "train", "y": "test"}, {"x": "slide:x", "y": "slide:y"}) == {}
