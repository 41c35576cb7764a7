"""Labels, train/test splits and shards of a dataset (shared by ``data_tools dataset`` and ``c16``)."""

from __future__ import annotations

import csv
import math
import re
import unicodedata
from pathlib import Path

import numpy as np

from data_tools.errors import HistojaxDataError

POSITIVE = {"1", "tumour", "tumor", "positive", "pos", "malignant", "metastasis", "macro", "micro", "true", "yes"}
NEGATIVE = {"0", "normal", "negative", "neg", "benign", "false", "no"}
NAME_COLUMNS = ("slide", "name", "slide_id", "slide_name", "image", "filename", "case_id")
LABEL_COLUMNS = ("label", "class", "target", "diagnosis", "y")


def parse_label(value: str, where, row: int) -> int:
    """0 or 1 from a label cell (``1`` / ``tumour`` / ``Tumor`` / ``positive`` ... or ``0`` / ``normal`` /
    ``negative`` ...; case-insensitive); a clear error naming the file and row otherwise."""
    v = str(value).strip().lower()
    if v in POSITIVE:
        return 1
    if v in NEGATIVE:
        return 0
    raise HistojaxDataError(
        where, f"row {row}: label {value!r} is neither tumour (1, Tumor, positive) nor normal (0, Normal, negative)"
    )


def slide_key(text: str) -> str:
    """A slide name as matched across files: the file name without its slide extension(s)."""
    name = Path(str(text).strip()).name
    for ext in (
        ".ome.tiff",
        ".ome.tif",
        ".qptiff",
        ".tiff",
        ".tif",
        ".btf",
        ".tf8",
        ".tf2",
        ".svs",
        ".ndpi",
        ".mrxs",
        ".scn",
        ".bif",
        ".vms",
        ".vmu",
        ".svslide",
        ".dcm",
        ".h5",
        ".xml",
        ".geojson",
        ".json",
    ):
        if name.lower().endswith(ext):
            return name[: -len(ext)]
    return name


MAX_LABEL_TABLE_BYTES = 64 * 2**20
"""A label table larger than this (64 MiB, millions of rows) is refused before it is read."""


def _label_table_text(path: Path) -> str:
    """The text of a label table: UTF-8 (with or without a BOM) or UTF-16 with a BOM; anything else, a FIFO
    or a file over :data:`MAX_LABEL_TABLE_BYTES` is an error naming the file."""
    import os
    import stat

    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise HistojaxDataError(path, "the label table is not a regular file (a folder, FIFO or device)")
        if st.st_size > MAX_LABEL_TABLE_BYTES:
            raise HistojaxDataError(
                path,
                f"the label table is {st.st_size / 2**20:.0f} MiB, over the "
                f"{MAX_LABEL_TABLE_BYTES // 2**20} MiB a table of slide labels needs",
            )
        data = path.read_bytes()
    except OSError as e:
        raise HistojaxDataError(path, f"cannot read the label table ({e.strerror or e})") from None
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        encoding = "utf-16"
    else:
        encoding = "utf-8-sig"
    try:
        text = data.decode(encoding)
    except UnicodeDecodeError as e:
        raise HistojaxDataError(
            path,
            f"the label table is not {'UTF-16' if encoding == 'utf-16' else 'UTF-8'} text "
            f"(byte {data[e.start]:#04x} at offset {e.start}); save it as UTF-8 (UTF-8 "
            "with a BOM and UTF-16 with a BOM are read too)",
        ) from None
    if "\x00" in text:
        raise HistojaxDataError(
            path, "the label table holds NUL characters: not a text table (UTF-16 without a BOM? save it as UTF-8)"
        )
    return text


def read_label_table(path) -> tuple[dict[str, int], dict[str, str]]:
    """``(labels, splits)`` from a CSV: a header naming a slide column (``slide``, ``name``, ``slide_id``,
    ...) and a label column (``label``, ``class``, ...), optionally ``split`` (train/test); or no header,
    rows ``name,label,...`` (CAMELYON16's ``reference.csv``: ``Test_001,Tumor,Macro,Primary``). Names are
    matched without extension and case-insensitively, so ``S1`` and ``s1`` are one slide. Text: UTF-8
    (a BOM allowed) or UTF-16 with a BOM. Rows naming one slide with different labels or splits, unknown
    label values or split values, undecodable text are errors naming the file and the rows."""
    import csv as _csv

    path = Path(path)
    text = _label_table_text(path)
    try:
        rows = [r for r in csv.reader(text.splitlines()) if r and any(c.strip() for c in r)]
    except _csv.Error as e:
        raise HistojaxDataError(path, f"not a readable CSV table ({e})") from None
    if not rows:
        raise HistojaxDataError(path, "the label table is empty")
    head = [c.strip().lower() for c in rows[0]]
    name_col = next((head.index(c) for c in NAME_COLUMNS if c in head), None)
    label_col = next((head.index(c) for c in LABEL_COLUMNS if c in head), None)
    split_col = head.index("split") if "split" in head else None
    if name_col is None and label_col is None:  # no header: name,label,...
        name_col, label_col, start = 0, 1, 0
    elif name_col is None or label_col is None:
        raise HistojaxDataError(
            path,
            f"the header {rows[0]} needs a slide column (one of {NAME_COLUMNS}) and a "
            f"label column (one of {LABEL_COLUMNS})",
        )
    else:
        start = 1
    labels: dict[str, int] = {}
    splits: dict[str, str] = {}
    first: dict[str, tuple[int, str]] = {}  # case-folded name -> (row, name as written) of its first row
    for i, row in enumerate(rows[start:], start=start + 1):
        if len(row) <= max(name_col, label_col):
            raise HistojaxDataError(path, f"row {i}: expected a slide name and a label, got {row}")
        name = slide_key(row[name_col])
        if not name:
            raise HistojaxDataError(path, f"row {i}: the slide name is empty")
        key = name.lower()
        label = parse_label(row[label_col], path, i)
        split = None
        if split_col is not None and len(row) > split_col and row[split_col].strip():
            split = row[split_col].strip().lower()
            if split not in ("train", "test"):
                raise HistojaxDataError(path, f"row {i}: split {row[split_col]!r} must be train or test")
        if key in first:
            j, was = first[key]
            if labels[was] != label:
                raise HistojaxDataError(
                    path,
                    f"rows {j} ({was!r}, label {labels[was]}) and {i} ({name!r}, label "
                    f"{label}) name one slide (names are matched ignoring case) with "
                    "different labels; keep one row",
                )
            if splits.get(was) != split:
                raise HistojaxDataError(
                    path,
                    f"rows {j} ({was!r}, split {splits.get(was)}) and {i} ({name!r}, split "
                    f"{split}) name one slide (names are matched ignoring case) with "
                    "different splits; keep one row",
                )
            continue
        first[key] = (i, name)
        labels[name] = label
        if split is not None:
            splits[name] = split
    if splits and set(splits) != set(labels):
        missing = sorted(set(labels) - set(splits))
        raise HistojaxDataError(
            path,
            f"the split column is empty for {len(missing)} slide(s), e.g. {missing[:3]}; "
            "give every slide a split or none",
        )
    return labels, splits


def _seeded_test(names, labels: dict[str, int], test_fraction: float, seed: int, members: dict[str, list[str]]):
    """The test side of :func:`seeded_split` (a set of names), ``members``: group key -> its sorted names."""
    keys = sorted(members)
    order = [keys[i] for i in np.random.default_rng([int(seed), 22]).permutation(len(keys))]
    test: set[str] = set()
    for label in sorted({labels[n] for n in names}):
        n_label = sum(labels[n] == label for n in names)
        cap = math.floor(test_fraction * n_label)
        if test_fraction > 0 and n_label >= 2:
            cap = max(cap, 1)
        taken = 0
        for g in order:
            if any(m in test for m in members[g]) or labels[members[g][0]] != label:
                continue
            size = sum(labels[m] == label for m in members[g])
            if taken + size <= cap:
                test.update(members[g])
                taken += size
    return test


def seeded_split(
    names, labels: dict[str, int], test_fraction: float, seed: int, groups: dict[str, str] | None = None
) -> tuple[list[str], list[str]]:
    """Train/test by slide, stratified by label: for each label, ``floor(test_fraction · n)`` slides (at
    least one while the label has two or more) go to test in a seeded order. ``groups`` (name → group
    key) keeps slides of one group (e.g. a patient) on one side. Deterministic given ``seed`` and the
    set of names (not their order). A ``test_fraction > 0`` whose grouped split leaves a side empty (every
    patient holds more slides than the fraction of a label) is refused in one line with the counts and the
    smallest ``--test-fraction`` that would give both sides slides."""
    if not 0 <= test_fraction < 1:
        raise HistojaxDataError(None, f"--test-fraction {test_fraction} must be in [0, 1)")
    names = sorted(names)
    groups = groups or {}
    members: dict[str, list[str]] = {}
    for n in names:
        members.setdefault(groups.get(n, n), []).append(n)
    test = _seeded_test(names, labels, test_fraction, seed, members)
    biggest = max((len(m) for m in members.values()), default=1)
    if test_fraction > 0 and biggest > 1 and len(members) >= 2 and (not test or len(test) == len(names)):
        works = next(
            (
                f / 100
                for f in range(1, 100)
                if 0 < len(_seeded_test(names, labels, f / 100, seed, members)) < len(names)
            ),
            None,
        )
        side = "test" if not test else "train"
        raise HistojaxDataError(
            None,
            f"--test-fraction {test_fraction:g}: {len(names)} slides in {len(members)} patients (up to "
            f"{biggest} slides each; the slides of one patient stay on one side): the seeded split leaves the "
            f"{side} side empty (a {test_fraction:g} share of each label is fewer slides than a whole patient "
            "holds); "
            + (
                f"use --test-fraction {works:.2f} or more, or give a split column"
                if works is not None
                else "no --test-fraction gives both sides slides: give a split column, or use --folds K"
            ),
        )
    return [n for n in names if n not in test], [n for n in names if n in test]


def grouped_split(names: list[str], donors: dict[str, str], test_fraction: float, seed: int) -> tuple[list, list]:
    """Train/test by slide: a tumour slide and the normal slide lending it tissue are one group (same
    side); groups go to test in a seeded order while the test side holds at most ``test_fraction`` of
    the tumour slides and of the normal slides; each side keeps at least one of each kind when it can.
    ``c16``'s split (``split_slides`` there; kept as it was so its published figures stay reproducible):
    a slide is a tumour slide when its name starts with ``tumor``."""
    parent = {n: n for n in names}
    for t, d in donors.items():
        if d in parent:
            parent[t] = d
    groups: dict[str, list[str]] = {}
    for n in names:
        groups.setdefault(parent[n], []).append(n)
    keys = sorted(groups)
    order = [keys[i] for i in np.random.default_rng([seed, 13]).permutation(len(keys))]
    is_t = lambda n: n.lower().startswith("tumor")  # noqa: E731
    n_t, n_n = sum(map(is_t, names)), sum(not is_t(n) for n in names)
    cap_t, cap_n = max(1, math.floor(test_fraction * n_t)), max(1, math.floor(test_fraction * n_n))
    test: list[str] = []
    order = [g for g in order if any(map(is_t, groups[g]))] + [g for g in order if not any(map(is_t, groups[g]))]
    for g in order:
        tt = sum(map(is_t, test)) + sum(map(is_t, groups[g]))
        tn = sum(not is_t(n) for n in test) + sum(not is_t(n) for n in groups[g])
        if tt <= min(cap_t, n_t - 1) and tn <= min(cap_n, n_n - 1):
            test += groups[g]
    return [n for n in names if n not in test], [n for n in names if n in test]


PATIENT_COLUMNS = ("patient", "patient_id", "case_submitter_id", "submitter_id")
"""Label-table columns naming a slide's patient (slides of one patient stay on one side of every fold)."""
TCGA_BARCODE = re.compile(r"^(TCGA-[A-Z0-9]{2}-[A-Z0-9]{4})(?:-|$)", re.IGNORECASE)
"""A TCGA slide name (``TCGA-A1-A0SB-01Z-00-DX1...``): its first three fields are the patient."""


def read_patient_column(path) -> dict[str, str]:
    """Slide name → patient from a label table's ``patient`` column (or ``patient_id``, ``case_submitter_id``,
    ``submitter_id``); ``{}`` when the table has no such column. Names as :func:`read_label_table` reads
    them; a row with an empty patient cell is an error naming the file and row."""
    path = Path(path)
    try:
        rows = [r for r in csv.reader(_label_table_text(path).splitlines()) if r and any(c.strip() for c in r)]
    except csv.Error as e:  # e.g. a cell over the csv module's field limit
        raise HistojaxDataError(path, f"not a readable CSV table ({e})") from None
    if not rows:
        return {}
    head = [c.strip().lower() for c in rows[0]]
    name_col = next((head.index(c) for c in NAME_COLUMNS if c in head), None)
    patient_col = next((head.index(c) for c in PATIENT_COLUMNS if c in head), None)
    if name_col is None or patient_col is None:
        return {}
    out: dict[str, str] = {}
    first: dict[str, tuple[int, str]] = {}  # case-folded name -> (row, name as written) of its first row
    for i, row in enumerate(rows[1:], start=2):
        name = slide_key(row[name_col]) if len(row) > name_col else ""
        patient = row[patient_col].strip() if len(row) > patient_col else ""
        if name and not patient_key(patient):  # empty, or only invisible characters (a zero-width space)
            raise HistojaxDataError(
                path,
                f"row {i}: the {rows[0][patient_col].strip()} cell of {name!r} is empty; "
                "give every slide its patient or drop the column",
            )
        if not name:
            continue
        if name.lower() in first:
            j, was = first[name.lower()]
            if patient_key(out[was]) != patient_key(patient):  # "P1" and "p1 " are one patient
                raise HistojaxDataError(
                    path,
                    f"rows {j} and {i} list slide {name!r} with two patients ({_cut(out[was])} "
                    f"and {_cut(patient)}); a slide belongs to one patient: keep one row",
                )
            continue
        first[name.lower()] = (i, name)
        out[name] = patient
    return out


def _cut(text: str, most: int = 80) -> str:
    """``repr(text)`` cut to ``most`` characters (a refusal quoting a patient id stays one short line)."""
    shown = repr(text)
    return shown if len(shown) <= most else shown[: most - 3] + "..."


def patient_key(text: str) -> str:
    """A patient id as the grouping compares it: surrounding whitespace stripped, inner runs of whitespace one
    space, case folded, and a TCGA barcode (``TCGA-A1-A0SB-01Z-...``, in a patient cell or a slide name) cut to its
    patient (``tcga-a1-a0sb``): ``"P1 "``, ``"p1"`` and ``"P1"`` are one patient. Unicode is compared in its NFKC
    form with its invisible format characters (zero-width spaces and joiners, a BOM, a soft hyphen) dropped: a cell
    pasted from a web page or typed on another system is the same patient; ``ß`` folds to ``ss``, while the
    dotted capital ``İ`` stays apart from ``i`` and ``I`` (Python's case folding)."""
    text = unicodedata.normalize("NFKC", str(text))  # "é" composed or not, a full-width "Ｐ１" are one spelling
    text = " ".join("".join(c for c in text if unicodedata.category(c) != "Cf").split())  # zero-width, BOM
    if m := TCGA_BARCODE.match(text):
        text = m.group(1)
    return text.casefold()


def patient_groups(names, patients: dict[str, str] | None = None) -> tuple[dict[str, str], str]:
    """``(name → patient, how)``: the label table's patient column (``patients``, matched ignoring case) where it
    names the slide, else the patient of a TCGA barcode (``TCGA-XX-XXXX``), else the slide itself; ``how`` says
    which rule grouped the slides (for ``dataset.json``). The one grouping of every split (the default split, the
    folds, the head fits' and readers' validation shares: :func:`baselines.validation.units`): ids are compared
    as :func:`patient_key` gives them (case and whitespace ignored), and each group is named by its first
    spelling (slides in sorted order), so a cohort spelled consistently keeps the keys (and splits) it had."""
    given = {k.lower(): v for k, v in (patients or {}).items()}
    out, used, spelling = {}, set(), {}
    for n in sorted(names):
        if n.lower() in given:
            pid, rule = " ".join(str(given[n.lower()]).split()), "the label table's patient column"
        elif m := TCGA_BARCODE.match(n.strip()):
            pid, rule = m.group(1).upper(), "the TCGA barcode's patient (TCGA-XX-XXXX)"
        else:
            out[n], rule = f"slide:{n}", "one slide per patient"
            used.add(rule)
            continue
        out[n] = "patient:" + spelling.setdefault(patient_key(pid), pid)
        used.add(rule)
    return {n: out[n] for n in names}, "; ".join(sorted(used)) or "one slide per patient"


def patients_on_both_sides(split: dict[str, str], groups: dict[str, str]) -> dict[str, dict[str, list[str]]]:
    """The patients a given split puts on more than one side: ``{patient: {side: [slide names]}}`` (``split``: name
    → side, ``groups``: name → patient key as :func:`patient_groups` gives it; one-slide "patients" never count)."""
    sides: dict[str, dict[str, list[str]]] = {}
    for n in sorted(split):
        sides.setdefault(groups.get(n, f"slide:{n}"), {}).setdefault(split[n], []).append(n)
    return {g.split(":", 1)[1]: v for g, v in sorted(sides.items()) if len(v) > 1}


def kfold_split(
    names, labels: dict[str, int], k: int, seed: int, groups: dict[str, str] | None = None
) -> dict[str, int]:
    """Slide name → fold (0..k-1): ``k`` folds stratified by label, the slides of one group (a patient) in one
    fold. Groups (labelled by their highest label: a patient with a tumour slide counts as tumour) are dealt,
    largest first and then in a seeded order, each to the fold holding the fewest slides of its label (then the
    fewest slides, then the lowest index). Deterministic given ``seed`` and the set of names (not their order).
    Refused (one line): ``k < 2``, or fewer than ``k`` groups of a label present (a fold would hold none of it,
    so neither AUC nor a detection reader could be scored on it)."""
    if isinstance(k, bool) or not isinstance(k, int) or k < 2:
        raise HistojaxDataError(None, f"--folds {k!r} must be a whole number >= 2")
    names = sorted(names)
    groups = groups or {}
    members: dict[str, list[str]] = {}
    for n in names:
        members.setdefault(groups.get(n, n), []).append(n)
    keys = sorted(members)
    glabel = {g: max(int(labels[m]) for m in members[g]) for g in keys}
    for label in sorted(set(glabel.values())):
        count = sum(v == label for v in glabel.values())
        if count < k:
            kind = "tumour" if label == 1 else "normal"
            raise HistojaxDataError(
                None,
                f"--folds {k} needs at least {k} {kind} patients (slides of one patient stay "
                f"in one fold); there are {count}: give fewer folds",
            )
    order = [keys[i] for i in np.random.default_rng([int(seed), 31]).permutation(len(keys))]
    order.sort(key=lambda g: -len(members[g]))  # stable: the seeded order within one size
    per_label = np.zeros((k, 2), dtype=np.int64)
    total = np.zeros(k, dtype=np.int64)
    fold: dict[str, int] = {}
    for g in order:
        lab = glabel[g]
        f = min(range(k), key=lambda i: (per_label[i, lab], total[i], i))
        for m in members[g]:
            fold[m] = f
        per_label[f, lab] += len(members[g])
        total[f] += len(members[g])
    return dict(sorted(fold.items()))


def folds_record(fold: dict[str, int], k: int, seed: int, pool: str, grouped_by: str) -> dict:
    """The ``folds`` entry of a dataset plan: ``k``, the ``pool`` folded (``"all"`` slides, or ``"train"``: the
    train side of a fixed split), ``seed``, the grouping rule and ``fold`` (slide name → 0..k-1)."""
    rule = (
        f"{k} folds, stratified by label, seeded (seed {seed}), slides of one patient in one fold ({grouped_by}); "
        + (
            "fold i: test = fold i, train = the other folds"
            if pool == "all"
            else "over the train side (the test set is fixed): fold i: validation = fold i, train = the other folds"
        )
    )
    return {"k": int(k), "pool": pool, "seed": int(seed), "grouped_by": grouped_by, "rule": rule, "fold": fold}


def fold_lists(folds: dict, built) -> dict:
    """``dataset.json``'s ``folds``: the plan's record (:func:`folds_record`) with ``lists`` (fold i → the
    ``bundles/NAME`` of its built slides, sorted) in place of ``fold``."""
    built = set(built)
    lists = [
        [f"bundles/{n}" for n, i in sorted(folds["fold"].items()) if i == f and n in built] for f in range(folds["k"])
    ]
    return {**{key: v for key, v in folds.items() if key != "fold"}, "lists": lists}


def parse_shard(text: str) -> tuple[int, int]:
    """``"I/N"`` → ``(I, N)`` with ``0 <= I < N`` (``$SLURM_ARRAY_TASK_ID/N`` with ``--array=0-(N-1)``)."""
    try:
        i, n = (int(v) for v in str(text).split("/"))
    except ValueError:
        raise HistojaxDataError(None, f"--shard {text!r}: expected I/N, e.g. 0/8 (shards 0 to N-1)") from None
    if not (n >= 1 and 0 <= i < n):
        raise HistojaxDataError(None, f"--shard {text!r}: I must be in 0..N-1 and N >= 1")
    return i, n


def shard_names(names, shard: tuple[int, int] | None) -> list[str]:
    """The names of shard ``(I, N)``: every N-th of the sorted names starting at the I-th (disjoint,
    covering, the same on every machine whatever the listing order)."""
    names = sorted(names)
    if shard is None:
        return names
    i, n = shard
    return names[i::n]


__all__ = [
    "PATIENT_COLUMNS",
    "TCGA_BARCODE",
    "fold_lists",
    "folds_record",
    "grouped_split",
    "kfold_split",
    "parse_label",
    "parse_shard",
    "patient_groups",
    "patient_key",
    "patients_on_both_sides",
    "read_label_table",
    "read_patient_column",
    "seeded_split",
    "shard_names",
    "slide_key",
]
