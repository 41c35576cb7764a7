"""Every split keeps patients whole, through one grouping (:func:`data_tools.datasets.split.patient_groups`): the
default train / test split, the folds, and the validation shares the head fits and ``train_readers`` cut from a train
side (:func:`baselines.validation.split_train`, which reads the patients ``dataset.json`` records). Patient ids are
compared ignoring case and whitespace, TCGA barcodes by their patient. A grouped split that would leave a side empty
is refused with the counts and the ``--test-fraction`` that works; a fold left with one class is warned about. Pure
planning: no slide is read."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from baselines.validation import split_train, units
from data_tools.datasets.build import make_plan
from data_tools.datasets.split import fold_lists, patient_groups, patient_key, seeded_split
from data_tools.errors import HistojaxDataError
from histojax.datasets import with_fold


def _entries(root: Path, rows):
    """Discovered-slide stand-ins: ``rows`` of ``(name, label)``, no split given."""
    return [
        SimpleNamespace(
            name=n,
            label=lab,
            split=None,
            path=root / f"{n}.svs",
            annotation=None,
            annotation_kind=None,
            label_source="t",
        )
        for n, lab in rows
    ]


def new_user_cohort(root: Path, folds: int = 3, seed: int = 0) -> dict:
    """A new user's small cohort as ``histojax dataset --labels ... --folds 3`` plans it: 12 tumour and 12 normal
    slides, one slide a patient except patient ``PX``, who owns a tumour slide and a normal slide (``Tumor_101``,
    ``Normal_141``; the label table spells the patient ``PX`` and ``px ``). Returns the ``dataset.json`` the build
    would write (every slide built): ``train`` / ``test``, ``labels``, ``folds``, ``patients``."""
    rows = [(f"Tumor_{100 + i:03d}", 1) for i in range(12)] + [(f"Normal_{140 + i:03d}", 0) for i in range(12)]
    patients = {n: f"P-{n}" for n, _ in rows} | {"Tumor_101": "PX", "Normal_141": " px "}
    plan = make_plan(_entries(root, rows), root, {}, 0.25, seed, folds=folds, patients=patients)
    names = sorted(plan["slides"])
    return {
        "kind": "histojax dataset",
        "train": [f"bundles/{n}" for n in names if plan["slides"][n]["split"] == "train"],
        "test": [f"bundles/{n}" for n in names if plan["slides"][n]["split"] == "test"],
        "labels": {n: plan["slides"][n]["label"] for n in names},
        "slides": [],
        "folds": fold_lists(plan["folds"], names),
        "patients": plan["patients"],
    }


def _sides_of(entries_by_side: dict[str, list[str]]) -> set[str]:
    """The sides holding patient PX's slides."""
    return {side for side, entries in entries_by_side.items() for e in entries if Path(e).name in PX}


PX = ("Tumor_101", "Normal_141")


@pytest.mark.parametrize("seed", range(6))
def test_no_split_of_a_new_users_cohort_puts_a_patient_on_both_sides(tmp_path, seed):
    spec = new_user_cohort(tmp_path, seed=seed)
    assert set(spec["patients"]) >= set(PX) and spec["patients"]["Tumor_101"] == spec["patients"]["Normal_141"]
    assert len(_sides_of({"train": spec["train"], "test": spec["test"]})) == 1  # the default split
    assert len({i for i, lst in enumerate(spec["folds"]["lists"]) for e in lst if Path(e).name in PX}) == 1
    shares = [spec] + [with_fold(spec, i) for i in range(3)]  # the train split's share, and each fold's train side's
    for fraction in (0.2, 0.3, 0.5):
        for split_seed in range(4):
            for side in shares:
                kept, held = split_train(side, fraction, split_seed)
                assert len(_sides_of({"kept": kept, "validation": held})) <= 1, (fraction, split_seed)


def test_a_validation_share_keeps_a_recorded_patient_in_one_unit():
    spec = {"train": ["bundles/a", "bundles/b", "bundles/c", "bundles/d"], "labels": {"a": 1, "b": 0, "c": 1, "d": 0}}
    assert units(spec) == [["bundles/a"], ["bundles/b"], ["bundles/c"], ["bundles/d"]]
    spec["patients"] = {"a": "P1", "b": "p1 "}  # one patient, spelled twice
    assert units(spec) == [["bundles/a", "bundles/b"], ["bundles/c"], ["bundles/d"]]
    tcga = {"train": ["bundles/TCGA-AA-0001-01Z-00-DX1", "bundles/tcga-aa-0001-11Z-00-DX1", "bundles/x"]}
    assert units(tcga)[0] == ["bundles/TCGA-AA-0001-01Z-00-DX1", "bundles/tcga-aa-0001-11Z-00-DX1"]


def test_patient_ids_and_tcga_barcodes_are_grouped_ignoring_case_and_whitespace():
    assert patient_key(" P 1 ") == patient_key("p  1") == "p 1"
    assert patient_key("TCGA-A1-A0SB-01Z-00-DX1") == patient_key("tcga-a1-a0sb") == "tcga-a1-a0sb"
    names = ["a", "b", "c", "TCGA-A1-A0SB-11Z-00-DX1", "tcga-a1-a0sb-01Z-00-DX1", "z"]
    groups, how = patient_groups(names, {"a": "P1", "B": " p1", "c": "TCGA-A1-A0SB-01Z"})
    assert groups["a"] == groups["b"] == "patient:P1"  # named by its first spelling
    assert groups["c"] == groups["TCGA-A1-A0SB-11Z-00-DX1"] == groups["tcga-a1-a0sb-01Z-00-DX1"]
    assert groups["z"] == "slide:z" and "patient column" in how and "TCGA" in how


def test_a_cohort_spelled_consistently_keeps_its_split(tmp_path):
    """Consistent ids give the keys (and so the seeded split) they gave before the ids were normalised."""
    rows = [(f"s{i:02d}", i % 2) for i in range(16)]
    patients = {n: f"Patient_{i // 2}" for i, (n, _) in enumerate(rows)}
    groups, _ = patient_groups([n for n, _ in rows], patients)
    assert set(groups.values()) == {f"patient:Patient_{i}" for i in range(8)}


def test_a_grouped_split_leaving_the_test_side_empty_is_refused_with_what_works(tmp_path):
    """12 slides in 6 two-slide patients: a 0.2 share of a label (1 slide) is less than any patient holds."""
    names = [f"s{i:02d}" for i in range(12)]
    labels = {n: int(i < 6) for i, n in enumerate(names)}
    groups = {n: f"p{i // 2}" for i, n in enumerate(names)}
    with pytest.raises(HistojaxDataError) as err:
        seeded_split(names, labels, 0.2, 0, groups)
    line = str(err.value)
    assert "\n" not in line and "12 slides in 6 patients" in line and "test side empty" in line
    assert "use --test-fraction 0.34 or more" in line
    train, test = seeded_split(names, labels, 0.34, 0, groups)
    assert train and test and not {groups[n] for n in train} & {groups[n] for n in test}
    rows = [(n, labels[n]) for n in names]
    with pytest.raises(HistojaxDataError, match="--test-fraction 0.2: 12 slides in 6 patients"):
        make_plan(_entries(tmp_path, rows), tmp_path, {}, 0.2, 0, patients=groups)  # refused before any build
    assert seeded_split(names, labels, 0.2, 0) != ([], [])  # one slide a patient: the split it always had


def test_a_fold_left_with_one_class_is_warned_naming_the_fold_and_its_counts():
    from data_tools.datasets.cli import one_class_fold_lines

    dataset = {"folds": {"lists": [["bundles/a", "bundles/b"], ["bundles/c"]]}}
    labels = {"a": 1, "b": 0, "c": 1}
    lines = one_class_fold_lines(dataset, labels, {"d": "unreadable"})
    assert len(lines) == 1 and "fold 1 holds 1 tumour and 0 normal slides" in lines[0]
    assert "1 failed slide(s)" in lines[0] and "\n" not in lines[0]
    both = {"folds": {"lists": [["bundles/a", "bundles/b"], ["bundles/c", "bundles/e"]]}}
    assert one_class_fold_lines(both, {**labels, "e": 0}, {}) == []


def test_a_slide_listed_twice_with_one_patient_spelled_twice_is_one_patient(tmp_path):
    from data_tools.datasets.split import read_patient_column

    table = tmp_path / "labels.csv"
    table.write_text("slide,label,patient\nA,1,P1\nB,0,P2\nA,1, p1 \n")
    assert read_patient_column(table) == {"A": "P1", "B": "P2"}


def test_a_built_dataset_records_its_patients_and_resumes_a_plan_written_before_them(tmp_path, capsys):
    """``histojax dataset --labels`` (a patient column; t0 and t1 one patient) writes ``patients`` in dataset.json;
    a plan.json written before the patients were recorded is agreed to (same labels, same patients)."""
    import json

    from fold_helpers import build_folded

    from data_tools.__main__ import main as data_main

    ds = build_folded(tmp_path, folds=2)
    spec = json.loads((ds / "dataset.json").read_text())
    assert spec["patients"]["t0"] == spec["patients"]["t1"] == "PT"
    kept, held = split_train(spec, 0.5, 0)
    assert len(_sides_of_names({"kept": kept, "validation": held}, ("t0", "t1"))) == 1
    plan = json.loads((ds / "plan.json").read_text())
    del plan["patients"]
    (ds / "plan.json").write_text(json.dumps(plan))
    argv = ["dataset", str(tmp_path / "S"), "--out", str(ds), "--labels", str(tmp_path / "labels.csv")]
    argv += ["--levels", "3", "--tile-size", "64", "--quiet", "--folds", "2"]
    assert data_main(argv) == 0  # resumed: not refused as another cohort
    plan = json.loads((ds / "plan.json").read_text())
    (ds / "plan.json").write_text(json.dumps({**plan, "patients": {**plan["patients"], "t1": "OTHER"}}))
    assert data_main(argv) == 2  # started with other patients: refused, saying so
    assert "started with other patients" in capsys.readouterr().err


def _sides_of_names(entries_by_side: dict[str, list[str]], names) -> set[str]:
    return {side for side, entries in entries_by_side.items() for e in entries if Path(e).name in names}
