"""k-fold cross-validation splits: ``histojax dataset … --folds K`` / ``c16 --folds K`` write K stratified,
patient-grouped, seeded folds to ``dataset.json``; ``make(..., split=, fold=i)`` picks fold i's sides (train = the
other folds; test / validation = fold i); a dataset without folds and an out-of-range fold are refused in a line."""

from __future__ import annotations

import collections
import json
import shutil

import pytest
from fold_helpers import build_folded

import histojax
from data_tools.__main__ import main as data_main
from data_tools.datasets.build import write_dataset_index
from data_tools.datasets.split import kfold_split, patient_groups, read_patient_column
from data_tools.errors import BundleError, HistojaxDataError
from histojax.datasets import dataset_slides


# ------------------------------------------------------------------ the fold rule
def test_folds_are_stratified_by_label_and_cover_every_slide():
    names = [f"s{i:02d}" for i in range(23)]
    labels = {n: int(i % 3 == 0) for i, n in enumerate(names)}  # 8 tumour, 15 normal
    fold = kfold_split(names, labels, 4, seed=0)
    assert sorted(fold) == sorted(names) and set(fold.values()) == {0, 1, 2, 3}
    for label in (0, 1):
        counts = collections.Counter(fold[n] for n in names if labels[n] == label)
        assert max(counts.values()) - min(counts.values()) <= 1, (label, counts)


def test_folds_are_deterministic_and_seeded():
    names = [f"s{i:02d}" for i in range(20)]
    labels = {n: int(i < 8) for i, n in enumerate(names)}
    a = kfold_split(names, labels, 5, seed=3)
    assert kfold_split(list(reversed(names)), labels, 5, seed=3) == a  # not the listing order
    assert any(kfold_split(names, labels, 5, seed=s) != a for s in (4, 5, 6))


def test_slides_of_one_patient_stay_in_one_fold():
    names = [
        "TCGA-A1-A0SB-01Z-00-DX1",
        "TCGA-A1-A0SB-01Z-00-DX2",
        "TCGA-A1-A0SD-01Z-00-DX1",
        "TCGA-B6-A0RE-01Z-00-DX1",
        "TCGA-B6-A0RE-01Z-00-DX2",
        "TCGA-B6-A0RE-01Z-00-DX3",
        "TCGA-C8-A12L-01Z-00-DX1",
        "TCGA-E2-A14N-01Z-00-DX1",
        "p1-a",
        "p1-b",
        "x",
        "y",
    ]
    labels = dict(zip(names, [1, 1, 0, 0, 0, 0, 1, 0, 1, 1, 0, 1]))  # 4 tumour and 4 normal patients
    groups, how = patient_groups(names, {"p1-a": "P1", "P1-B": "P1"})  # the table's names, matched ignoring case
    assert "TCGA barcode" in how and "patient column" in how
    assert groups["TCGA-B6-A0RE-01Z-00-DX2"] == groups["TCGA-B6-A0RE-01Z-00-DX3"]
    assert groups["p1-a"] == groups["p1-b"] and groups["x"] != groups["y"]
    for seed in range(10):
        fold = kfold_split(names, labels, 3, seed, groups)
        for g in set(groups.values()):
            assert len({fold[n] for n in names if groups[n] == g}) == 1, (seed, g)


def test_too_few_patients_of_a_label_or_k_below_2_are_refused():
    names = ["a", "b", "c", "d", "e"]
    labels = {"a": 1, "b": 1, "c": 0, "d": 0, "e": 0}
    with pytest.raises(HistojaxDataError, match="--folds 3 needs at least 3 tumour patients.*there are 2"):
        kfold_split(names, labels, 3, 0)
    with pytest.raises(HistojaxDataError, match="--folds 1 must be a whole number >= 2"):
        kfold_split(names, labels, 1, 0)
    with pytest.raises(HistojaxDataError, match="at least 2 tumour patients.*there are 1"):  # a and b: one patient
        kfold_split(names, labels, 2, 0, {"a": "P", "b": "P"})


def test_the_patient_column_is_read(tmp_path):
    p = tmp_path / "labels.csv"
    p.write_text("slide,label,patient\ns1.svs,1,P1\ns2,0,P1\ns3,0,P2\n")
    assert read_patient_column(p) == {"s1": "P1", "s2": "P1", "s3": "P2"}
    p.write_text("slide,label\ns1,1\n")
    assert read_patient_column(p) == {}
    p.write_text("slide,label,patient\ns1,1,\n")
    with pytest.raises(HistojaxDataError, match=r"labels\.csv: row 2: the patient cell of 's1' is empty"):
        read_patient_column(p)


# ------------------------------------------------------------------ dataset --folds, make(fold=)
@pytest.fixture(scope="module")
def folded(tmp_path_factory):
    """A 7-slide dataset (4 tumour, 3 normal by the label table; t0 and t1 one patient) with --folds 2."""
    return build_folded(tmp_path_factory.mktemp("folds"))


def test_dataset_json_records_the_folds(folded):
    ds = json.loads((folded / "dataset.json").read_text())
    folds = ds["folds"]
    assert folds["k"] == 2 and folds["pool"] == "all" and "patient column" in folds["grouped_by"]
    lists = folds["lists"]
    assert sorted(n for lst in lists for n in lst) == sorted(ds["train"] + ds["test"])  # a partition of the slides
    assert any("bundles/t0" in lst and "bundles/t1" in lst for lst in lists)  # one patient, one fold
    assert ("bundles/t0" in ds["test"]) == ("bundles/t1" in ds["test"])  # and one side of the default split
    assert ds["split_grouped_by"] == folds["grouped_by"] and "one patient on one side" in ds["split_rule"]
    for lst in lists:  # both labels in each fold
        assert {ds["labels"][n.split("/")[1]] for n in lst} == {0, 1}


def test_make_fold_picks_the_sides(folded):
    lists = json.loads((folded / "dataset.json").read_text())["folds"]["lists"]
    for i in range(2):
        test = {p.name for p in dataset_slides(folded, "test", i)}
        train = {p.name for p in dataset_slides(folded, "train", i)}
        assert test == {n.split("/")[1] for n in lists[i]} and not test & train
        assert test | train == {f"{c}{j}" for c, n in (("t", 4), ("n", 3)) for j in range(n)}
        assert {p.name for p in dataset_slides(folded, "validation", i)} == test
    env, params = histojax.make("HistoJAX-Easy-v0", dataset=folded, split="test", fold=1, verify=False)
    assert [b.path.name for b in env._bundles] == sorted(n.split("/")[1] for n in lists[1])
    env, _ = histojax.make("HistoJAX-Easy-v0", dataset=folded, verify=False)  # no fold: the single split, as before
    assert sorted(b.path.name for b in env._bundles) == sorted(
        n.split("/")[1] for n in json.loads((folded / "dataset.json").read_text())["train"]
    )


def test_fold_refusals_are_one_line(folded, tmp_path):
    with pytest.raises(BundleError, match=r"fold=2 is out of range: this dataset has 2 folds \(0 to 1\)"):
        histojax.make("HistoJAX-Easy-v0", dataset=folded, fold=2, verify=False)
    with pytest.raises(BundleError, match="fold=-1 is out of range"):
        dataset_slides(folded, "train", -1)
    plain = tmp_path / "plain"
    shutil.copytree(folded, plain)
    ds = json.loads((plain / "dataset.json").read_text())
    del ds["folds"]
    write_dataset_index(plain, ds)  # sealed again: a dataset built without --folds
    with pytest.raises(
        BundleError,
        match=r"fold=0: this dataset has no folds; build it with `histojax dataset "
        r"\.\.\. --folds K`",
    ) as e:
        histojax.make("HistoJAX-Easy-v0", dataset=plain, fold=0, verify=False)
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="fold=0 picks a fold of a dataset"):
        histojax.make("HistoJAX-Easy-v0", fold=0)


def test_folds_over_a_fixed_split_cut_the_train_side(folded, tmp_path):
    """A split column fixes the test set: the folds then cut the train side only (fold i = validation), and
    ``split="test"`` with a fold is refused (the fixed test set has no folds)."""
    slides = folded.parent / "S"
    rows = (
        ["slide,label,split"]
        + [f"t{j},1,{'test' if j == 3 else 'train'}" for j in range(4)]
        + [f"n{j},0,{'test' if j == 2 else 'train'}" for j in range(3)]
    )
    (tmp_path / "labels.csv").write_text("\n".join(rows) + "\n")
    out = tmp_path / "ds"
    assert (
        data_main(
            [
                "dataset",
                str(slides),
                "--out",
                str(out),
                "--labels",
                str(tmp_path / "labels.csv"),
                "--levels",
                "3",
                "--tile-size",
                "64",
                "--quiet",
                "--folds",
                "2",
            ]
        )
        == 0
    )
    ds = json.loads((out / "dataset.json").read_text())
    assert ds["folds"]["pool"] == "train"
    assert sorted(n for lst in ds["folds"]["lists"] for n in lst) == sorted(ds["train"])
    assert {p.name for p in dataset_slides(out, "validation", 0)} <= {f"t{j}" for j in range(3)} | {"n0", "n1"}
    with pytest.raises(BundleError, match="split='validation'; the test set is split='test' without fold"):
        dataset_slides(out, "test", 0)


def test_too_many_folds_for_the_dataset_is_one_line(folded, capsys):
    out = folded.parent / "too-many"
    code = data_main(
        [
            "dataset",
            str(folded.parent / "S"),
            "--out",
            str(out),
            "--labels",
            str(folded.parent / "labels.csv"),
            "--levels",
            "3",
            "--quiet",
            "--folds",
            "4",
        ]
    )
    err = capsys.readouterr().err.strip()
    assert (
        code == 2
        and "--folds 4 needs at least 4 normal patients (slides of one patient stay in one fold); there are 3" in err
        and len(err.splitlines()) == 1
    )
    assert not (out / "plan.json").exists()


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_c16_folds_keep_a_tumour_slide_with_its_donor(c16_small):
    """``c16 --folds 2`` (the shared small set is built with it): folds of the train side, a tumour slide in the
    fold of the normal slide lending it tissue; ``make`` on a C16 id takes ``fold=``."""
    out, version = c16_small
    ds = json.loads((out / "dataset.json").read_text())
    folds = ds["folds"]
    assert folds["k"] == 2 and folds["pool"] == "train"
    assert sorted(n for lst in folds["lists"] for n in lst) == sorted(ds["train"])
    donors = {s["name"]: s.get("tissue_donor") for s in ds["slides"]}
    where = {n.split("/")[1]: i for i, lst in enumerate(folds["lists"]) for n in lst}
    for t, d in donors.items():
        if t in where and d in where:
            assert where[t] == where[d], (t, d)
    assert any(t in where and d in where for t, d in donors.items())  # the check above checked something
    env, _ = histojax.make(f"HistoJAX-C16-Hard-{version}", dataset=out, split="validation", fold=0, verify=False)
    assert sorted(b.path.name for b in env.bundles) == sorted(n.split("/")[1] for n in folds["lists"][0])


# ------------------------------------------------------------------ --fold on the trainers, head fits and readers
def test_trainers_take_fold(folded):
    from baselines import ppo
    from baselines.common.env import make_env
    from baselines.harness.cli import config_from_args

    args = ppo.parse_args(["--env", "HistoJAX-Easy-v0", "--dataset", str(folded), "--fold", "1"])
    config = config_from_args(args, ppo.DEFAULTS)
    assert config["env_kwargs"]["fold"] == 1
    env, _ = make_env({**config, "env_kwargs": {**config["env_kwargs"], "verify": False}})
    assert sorted(b.path.name for b in env.bundles) == sorted(p.name for p in dataset_slides(folded, "train", 1))
    with pytest.raises(SystemExit, match="--fold needs --dataset DIR"):
        config_from_args(ppo.parse_args(["--fold", "0"]), ppo.DEFAULTS)


def test_head_fits_and_readers_read_the_fold(folded):
    from baselines.reading.slides import HeadDataError, read_spec

    lists = json.loads((folded / "dataset.json").read_text())["folds"]["lists"]
    spec = read_spec(folded, 0)  # head_fit, head_mil_fit, readers, diagnosis: --fold I
    assert spec["train"] == lists[1] and spec["test"] == spec["validation"] == lists[0] and spec["fold"] == 0
    assert read_spec(folded)["train"] == json.loads((folded / "dataset.json").read_text())["train"]  # no fold
    with pytest.raises(HeadDataError, match=r"dataset\.json: fold=3 is out of range: this dataset has 2 folds"):
        read_spec(folded, 3)


def test_budget_curve_refuses_folds_and_fold_together(folded, capsys):
    from baselines.reading import budget_curve

    assert budget_curve.main(["--dataset", str(folded), "--folds", "2", "--fold", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--folds K" in err and "not both" in err and len(err.splitlines()) == 1
