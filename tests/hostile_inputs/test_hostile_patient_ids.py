"""A hostile pass over the patients a dataset records (``patient_key`` / ``patient_groups`` in
:mod:`data_tools.datasets.split`, ``patients`` in ``dataset.json``): patient cells that differ only by invisible or
composed Unicode are one patient (a split keeps them on one side), an id of only a zero-width space is empty, an
over-long cell and two over-long ids of one slide are one short line; a hand-edited (and resealed) ``patients``
record of the wrong types is refused naming ``dataset.json``; a ``dataset.json`` nested past the parser or not
UTF-8 is one line naming it (both were tracebacks)."""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import pytest

from baselines.reading.slides import read_spec
from baselines.validation import split_train, units
from data_tools.bundle_files.seals import DATASET_DIGEST, metadata_digest
from data_tools.datasets.index import read_dataset_json
from data_tools.datasets.split import patient_groups, patient_key, read_patient_column
from data_tools.errors import HistojaxDataError


@pytest.mark.parametrize(
    "a, b",
    [
        ("P1", "P1\u200b"),  # a zero-width space pasted from a web page: were two patients
        ("P1", "\ufeffP1"),  # a BOM (a cell of a table saved by another tool)
        ("P1", "P\u20601"),  # a word joiner
        ("P1", "P\u00ad1"),  # a soft hyphen
        ("Ｐ１", "P1"),  # full-width letters and digits (an East Asian keyboard)
        ("Jos\u00e9", "Jose\u0301"),  # é composed (NFC) and decomposed (NFD, macOS file names)
        ("Straße", "STRASSE"),  # case folding (was already one)
        ("p  1", " P 1 "),  # whitespace runs (was already one)
    ],
)
def test_patient_ids_differing_only_by_invisible_or_composed_unicode_are_one_patient(a, b):
    assert patient_key(a) == patient_key(b)
    groups, _ = patient_groups(["s1", "s2"], {"s1": a, "s2": b})
    assert groups["s1"] == groups["s2"] == "patient:" + " ".join(a.split())  # named by the first spelling


@pytest.mark.parametrize("a, b", [("P1", "P 1"), ("İ1", "i1"), ("I1", "ı1"), ("P1", "P2")])
def test_patient_ids_that_are_other_letters_stay_apart(a, b):
    assert patient_key(a) != patient_key(b)


def test_a_patient_id_equal_to_another_slides_name_is_not_that_slide():
    groups, _ = patient_groups(["A", "B", "C"], {"A": "B"})  # A's patient is named "B"; slide B has none
    assert groups == {"A": "patient:B", "B": "slide:B", "C": "slide:C"}
    assert units({"train": ["x/A", "x/B", "x/C"], "patients": {"A": "B"}}) == [["x/A"], ["x/B"], ["x/C"]]


def test_a_patient_cell_of_only_a_zero_width_space_is_empty(tmp_path):
    """Was: the invisible id "\\u200b" accepted as a patient (every such slide one patient)."""
    table = tmp_path / "labels.csv"
    table.write_text("slide,label,patient\nA,1,\u200b\nB,0,P2\n", encoding="utf-8")
    with pytest.raises(HistojaxDataError, match=r"row 2: the patient cell of 'A' is empty"):
        read_patient_column(table)


def test_over_long_patient_cells_are_one_short_line(tmp_path):
    table = tmp_path / "labels.csv"
    table.write_text("slide,label,patient\nA,1," + "x" * 200_000 + "\n")
    with pytest.raises(HistojaxDataError, match="not a readable CSV table") as e:  # was: a csv.Error traceback
        read_patient_column(table)
    assert str(table) in str(e.value)
    table.write_text("slide,label,patient\nA,1," + "x" * 100_000 + "\nA,1," + "y" * 100_000 + "\n")
    with pytest.raises(HistojaxDataError, match="two patients") as e:  # was: both ids quoted whole (200 KB)
        read_patient_column(table)
    assert len(str(e.value)) < 400


def _sealed(folder: Path, spec: dict) -> Path:
    folder.mkdir(exist_ok=True)
    body = {k: v for k, v in spec.items() if k != DATASET_DIGEST}
    (folder / "dataset.json").write_text(json.dumps({**body, DATASET_DIGEST: metadata_digest(body)}))
    return folder


SPEC = {"kind": "histojax dataset of real slides (data_tools dataset)", "train": ["b/A", "b/B", "b/C"], "test": []}


@pytest.mark.parametrize(
    "patients, words",
    [
        ({"A": 5, "B": 5}, "gives slide 'A' the patient 5"),  # were: one patient "5"
        ({"A": None, "B": None}, "the patient null"),  # were: one patient "None"
        ({"A": ["P"], "B": ["P"]}, 'the patient ["P"]'),
        ({"A": "", "B": ""}, 'the patient ""'),  # were: one patient of the empty id
        ({"A": "\u200b"}, 'the patient "\\u200b"'),
        ({"A" * 1000: 5}, "gives slide 'AAAA"),  # a long name: cut
        (["A", "B"], "its patients record is a JSON list"),  # was: silently ignored
        ("P1", "its patients record is a JSON str"),
    ],
)
def test_a_resealed_patients_record_of_the_wrong_types_is_refused_naming_the_file(tmp_path, patients, words):
    ds = _sealed(tmp_path / "ds", {**SPEC, "patients": patients})
    with pytest.raises(HistojaxDataError) as e:
        read_spec(ds)
    line = str(e.value)
    assert line.startswith(str(ds / "dataset.json")) and words in line and "\n" not in line and len(line) < 400


def test_a_patients_record_missing_a_slide_or_naming_an_extra_one_is_read(tmp_path):
    """A slide without a record is its own patient (a build records only slides grouped with others); a name of
    no slide of the dataset groups nothing."""
    ds = _sealed(tmp_path / "ds", {**SPEC, "patients": {"A": "P", "B": "p", "Z": "P"}})
    spec = read_spec(ds)
    assert units(spec) == [["b/A", "b/B"], ["b/C"]]
    kept, held = split_train({**spec, "labels": {"A": 1, "B": 1, "C": 1}}, 0.5, 0)
    assert {"b/A", "b/B"} <= set(kept) or {"b/A", "b/B"} <= set(held)
    spec = json.loads((ds / "dataset.json").read_text())  # edited without resealing: the seal refuses it
    (ds / "dataset.json").write_text(json.dumps({**spec, "patients": {"A": "P", "B": "Q"}}))
    with pytest.raises(HistojaxDataError, match="does not match its seal"):
        read_spec(ds)


@pytest.mark.parametrize(
    "data, words",
    [
        (b'{"train": ' + b"[" * 100_000 + b"]" * 100_000 + b"}", "nests its JSON deeper"),  # was: RecursionError
        (b'{"train": [], "note": "\xff"}', "is not UTF-8 text (byte 0xff at offset 23)"),  # was: UnicodeDecodeError
    ],
)
def test_a_dataset_json_nested_past_the_parser_or_not_utf8_is_one_line_naming_it(tmp_path, data, words):
    (tmp_path / "dataset.json").write_bytes(data)
    for read in (read_dataset_json, read_spec):
        with pytest.raises(HistojaxDataError, match=re.escape(words)) as e:
            read(tmp_path)
        assert str(e.value).startswith(str(tmp_path / "dataset.json"))


def test_a_built_dataset_groups_hostile_spellings_of_one_patient_and_keeps_them_on_one_side(tmp_path):
    """``histojax dataset --labels`` with t0, t1 and t2 spelled ``P1``, ``p1`` + a zero-width space and a full-width
    ``Ｐ１``: dataset.json records one patient for the three, and the default split keeps them on one side. Builds
    a 7-slide dataset (~5 s)."""
    from fold_helpers import SLIDES, build_folded

    real = Path(tmp_path / "labels.csv")
    spellings = {"t0": "P1", "t1": "p1\u200b", "t2": "Ｐ１"}
    orig_write = Path.write_text

    def hostile_table(self, text, *a, **k):  # build_folded writes the table: give t0-t2 the hostile spellings
        if self == real:
            rows = [f"{n},{lab},{spellings.get(n, n.upper())}" for n, lab in SLIDES]
            text = "slide,label,patient\n" + "\n".join(rows) + "\n"
        return orig_write(self, text, *a, **k)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Path, "write_text", hostile_table)
        ds = build_folded(tmp_path, folds=2)
    spec = read_dataset_json(ds)
    assert spec["patients"]["t0"] == spec["patients"]["t1"] == spec["patients"]["t2"] == "P1"
    side = {Path(e).name: s for s in ("train", "test") for e in spec[s]}
    assert side["t0"] == side["t1"] == side["t2"]
    folds = {Path(e).name: i for i, lst in enumerate(spec["folds"]["lists"]) for e in lst}
    assert folds["t0"] == folds["t1"] == folds["t2"]


@pytest.mark.parametrize("kind", ["fifo", "deep", "folder"])
def test_histojax_dataset_over_a_fifo_or_nested_plan_json_is_one_line_nothing_written(tmp_path, capsys, kind):
    """Was: ``plan.json`` a FIFO blocked ``histojax dataset --out DS`` for ever (``read_text``); one nested past the
    parser was a RecursionError traceback. The plan (where the patients are recorded) is read before anything is
    written."""
    import signal

    from data_tools.__main__ import main as data_main

    slides, out = tmp_path / "S", tmp_path / "ds"
    slides.mkdir()
    (slides / "a.tif").write_bytes(b"")  # never opened: the plan is refused first
    out.mkdir()
    plan = out / "plan.json"
    if kind == "fifo":
        os.mkfifo(plan)
    elif kind == "deep":
        plan.write_text("[" * 100_000 + "]" * 100_000)
    else:
        plan.mkdir()
    old = signal.signal(signal.SIGALRM, lambda *_: pytest.fail("blocked on plan.json"))
    signal.alarm(30)
    try:
        code = data_main(["dataset", str(slides), "--out", str(out), "--quiet"])
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "plan.json" in err[0], err
    assert sorted(p.name for p in out.iterdir()) == ["plan.json"]
