"""What a slide head was fitted on, and the one guard every scorer applies with it.

Every head fit (:mod:`baselines.reading.head_fit`, :mod:`~baselines.reading.head_mil_fit`,
:mod:`~baselines.reading.learned_head_fit`) records in its ``config.json`` the entry :data:`RECORD`
(:func:`fit_record`): the dataset (folder, ``kind`` and seal, ``dataset_sha256``), the split and fold it was fitted
on, and the slide names used for **fitting** and for **validation** (choosing a candidate or a checkpoint,
calibrating). Every scorer (``histojax evaluate --head``, ``readers``, ``budget-curve``, ``learned_head_fit
--score``, ``diagnosis``) calls :func:`check_scored` with the slides it is about to score: a slide the head was
fitted or validated on is refused (one line naming the head's ``config.json``, the slides and the way out), or, with
``--allow-fitting-slides``, warned about on stderr and scored.

Training runs record the same for their **policy** (:func:`write_run_record`: ``RUN/slides_seen.json``, the side
of the dataset trained on and the validation slides it held back); every scorer of a policy (``histojax evaluate``,
``readers --reader``, ``budget-curve --ppo``, ``diagnosis --navigator``) checks it with :func:`check_policy`
(:func:`check_record` of :func:`run_record`: an older run is checked from what its ``config.json`` names). With
:data:`FLAG`, what a scorer writes carries ``self_scored`` and ``scored_on_seen_slides`` (:func:`seen_mark`).

Slides are matched **by identity** (:func:`slide_identity`: ``camelyon16:NAME`` in a CAMELYON16 set, whose slides are
CAMELYON16's by name at any scale or encoder; else the SHA-256 of the slide file the bundle was built from), so a
renamed slide is still the slide seen; by **name** only where names can be trusted (:func:`seen_among`: the same
seal, a record without identities, a slide whose identity is unknown).

**Heads without the record** (heads fitted before it): a head whose ``config.json`` records a fit (``fitted_on``) is
taken to have been fitted on the **train split** of the dataset its ``fitted_on`` names when that is the scored one
or names none (the whole split, without folds; an older fold fit whose ``fitted_on`` records its ``fold``: that
fold's train side, the other folds); a head naming another dataset: that one's train split when it is here, by
identity, else a warning that its slides cannot be checked. The published heads and agents carry the record
(c16-full's train slides by CAMELYON16 name). A head that records no fit at all (built in code, uncalibrated) has
seen no slide.
"""

from __future__ import annotations

import json
import os
import stat
import sys
from pathlib import Path

from data_tools.errors import HistojaxDataError
from data_tools.metrics import json_safe

RECORD = "slides_seen"
"""Key of the fit record in a head's ``config.json`` (:func:`fit_record`)."""
FLAG = "--allow-fitting-slides"
"""The option that turns the refusal into a warning."""


class FittingSlidesError(HistojaxDataError):
    """A head asked to score slides it was fitted or validated on (one line naming its ``config.json``)."""


def _name(entry) -> str:
    return Path(str(entry)).name


def dataset_identity(dataset, spec: dict | None = None) -> dict:
    """``{"folder", "kind", "seal"}`` of a dataset: its resolved folder, ``dataset.json``'s ``kind`` and seal
    (``dataset_sha256``, None for an unsealed index; a derived validation split: its source's seal)."""
    from data_tools.bundle_files.seals import DATASET_DIGEST
    from data_tools.datasets.index import read_dataset_json

    if spec is None:
        try:
            spec = read_dataset_json(dataset)
        except (OSError, ValueError):
            spec = {}
    seal = spec.get(DATASET_DIGEST) if isinstance(spec, dict) else None
    return {
        "folder": str(Path(dataset).resolve()),
        "kind": spec.get("kind") if isinstance(spec, dict) else None,
        "seal": seal,
    }


C16_KIND = "CAMELYON16"
"""A ``dataset.json`` ``kind`` holding this word is a CAMELYON16 set: its slides are CAMELYON16's, by name."""


def slide_identity(dataset, entry, kind=None) -> str | None:
    """What identifies the slide of ``entry`` (a ``dataset.json`` entry ``bundles/NAME`` or a bundle path) of
    ``dataset`` whatever its name or dataset: ``"camelyon16:NAME"`` in a CAMELYON16 set (``kind``; every C16 set,
    at any scale or encoder, holds CAMELYON16's slides under their own names), else ``"sha256:HEX"``, the SHA-256 of
    the slide file the bundle was built from (its ``metadata.json``'s ``source.sha256``); None when neither is
    known (no ``metadata.json``, or one that records no hash)."""
    name = _name(entry)
    if C16_KIND in str(kind or ""):
        return f"camelyon16:{name}"
    folder = Path(str(entry))
    if not folder.is_absolute() and dataset is not None:
        folder = Path(dataset) / folder
        if len(Path(str(entry)).parts) == 1 and not folder.is_dir():  # a bare name: the dataset's bundles/NAME
            folder = Path(dataset) / "bundles" / name
    try:
        meta = json.loads((folder / "metadata.json").read_text())
        digest = (meta.get("source") or {}).get("sha256")
    except (OSError, ValueError, AttributeError):
        return None
    return f"sha256:{digest}" if isinstance(digest, str) and digest else None


def identities(dataset, entries, kind=None) -> dict[str, str]:
    """``{name: identity}`` (:func:`slide_identity`) of the ``entries`` of ``dataset`` whose identity is known and
    is theirs alone (two bundles built from one slide file are told apart by name only)."""
    out = {}
    for e in entries:
        ident = slide_identity(dataset, e, kind)
        if ident is not None:
            out[_name(e)] = ident
    counts: dict[str, int] = {}
    for ident in out.values():
        counts[ident] = counts.get(ident, 0) + 1
    return {n: i for n, i in out.items() if counts[i] == 1}


def fit_record(dataset, spec: dict, fold: int | None, fitted, validation, split: str = "train") -> dict:
    """The :data:`RECORD` entry of a head's ``config.json`` (or a run's ``slides_seen.json``): the dataset's
    identity (:func:`dataset_identity`, the seal of its ``dataset.json`` as read without a fold), ``split`` and
    ``fold`` fitted on, the sorted slide names of ``fitted`` (the slides whose labels trained or calibrated it) and
    ``validation`` (the slides that chose its candidate or checkpoint, or calibrated it), each a list of
    ``dataset.json`` entries or names, and ``identities`` (name → :func:`slide_identity`), by which a slide is known
    in another dataset or under another name."""
    from data_tools.datasets.index import read_dataset_json

    try:
        base = read_dataset_json(dataset)  # the index itself (spec may be a fold's sides)
    except (OSError, ValueError):
        base = spec
    ident = dataset_identity(dataset, base)
    return {
        "dataset": ident,
        "split": split,
        "fold": fold,
        "fitted": sorted({_name(e) for e in fitted}),
        "validation": sorted({_name(e) for e in validation}),
        "identities": dict(sorted(identities(dataset, [*fitted, *validation], ident["kind"]).items())),
    }


def head_config(head) -> dict:
    """The fit information a loaded head carries (its ``info``: ``config.json`` beyond its structure); ``{}`` when
    none."""
    try:
        info = json.loads(getattr(head, "info", "{}") or "{}")
    except (TypeError, ValueError):
        return {}
    return info if isinstance(info, dict) else {}


def _spec(dataset) -> dict | None:
    from data_tools.datasets.index import read_dataset_json

    try:
        spec = read_dataset_json(dataset)
    except (OSError, ValueError):
        return None
    return spec if isinstance(spec, dict) else None


def _assumed(info: dict, dataset) -> tuple[dict | None, str]:
    """The record a head without one is taken to have (:func:`slides_seen`): ``(record, source)``."""
    if "fitted_on" not in info or dataset is None:  # no dataset named (bundle folders given): nothing to assume
        return None, "none"
    fitted_on = info.get("fitted_on") if isinstance(info.get("fitted_on"), dict) else {}
    named = fitted_on.get("dataset")
    named_other = isinstance(named, str) and bool(named) and not _same_folder(named, dataset)
    if named_other:
        # fitted on another dataset: its own train split, when it is here (matched by identity), else unknown
        other = _spec(named)
        if other is None:
            return None, "unknown"
        dataset, spec = named, other
    else:
        spec = _spec(dataset)
        if spec is None:
            return None, "none"
    fold = fitted_on.get("fold")
    if isinstance(fold, int) and not isinstance(fold, bool):  # an older fold fit: the other folds' slides
        from histojax.datasets import with_fold

        try:
            spec = with_fold(spec, fold)
        except (HistojaxDataError, ValueError):
            pass  # the dataset has no such fold: its train split, as for any older head
    train = list(spec.get("train") or [])
    ident = dataset_identity(dataset, spec)
    record = {"dataset": ident, "fitted": sorted({_name(e) for e in train}), "validation": []}
    if named_other:  # another dataset's slides: known by identity in the scored one
        record["identities"] = identities(dataset, train, ident["kind"])
    return record, "assumed"


def _same_folder(a, b) -> bool:
    """Whether two dataset folders (a path, or a folder name as published records keep it) are one: the same
    resolved path, or the same folder name when either is a bare name."""
    pa, pb = Path(str(a)), Path(str(b))
    try:
        if pa.resolve() == pb.resolve():
            return True
    except OSError:
        pass
    bare = lambda p: len(p.parts) == 1  # noqa: E731
    return (bare(pa) or bare(pb)) and pa.name == pb.name


def slides_seen(head, dataset) -> tuple[set[str], set[str], str]:
    """``(fitted, validation, source)``: the slide names ``head`` was fitted and validated on and where that comes
    from: its :data:`RECORD` (``"recorded"``), else, for a head recording a fit but no slides (older heads), the
    train split of the dataset its ``fitted_on`` names when that is here (else of ``dataset``'s ``dataset.json``
    read without a fold: ``"assumed"``; ``"unknown"`` when it names another dataset that is not here), else nothing
    (``"none"``: a head built in code)."""
    record, source = record_of(head_config(head), dataset)
    if record is None:
        return set(), set(), source
    return set(map(str, record.get("fitted") or [])), set(map(str, record.get("validation") or [])), source


def record_of(info: dict, dataset) -> tuple[dict | None, str]:
    """``(record, source)`` of a head's ``config.json`` object ``info``: its :data:`RECORD` (``"recorded"``), else
    the one assumed for it (:func:`slides_seen`)."""
    rec = info.get(RECORD)
    if isinstance(rec, dict):
        return rec, "recorded"
    return _assumed(info, dataset)


def seen_among(record: dict | None, dataset, scored) -> tuple[list[str], list[str], dict[str, str]]:
    """``(fitted, validated, renamed)``: the names among ``scored`` (``dataset.json`` entries of ``dataset``, paths or
    names) that ``record`` (a :data:`RECORD` entry) saw in fitting, those it saw in validation only, and
    ``{scored name: recorded name}`` of those it knew by another name. A slide is seen when its identity
    (:func:`slide_identity`) is one the record holds, whatever its name; by its **name** only when the names can be
    trusted: the scored dataset has the record's seal, or the record holds no identities (written before them), or
    the scored slide's identity cannot be known. A slide of another dataset (another seal) that merely shares a
    name with a seen one is not seen."""
    if not isinstance(record, dict):
        return [], [], {}
    fitted = set(map(str, record.get("fitted") or []))
    validation = set(map(str, record.get("validation") or [])) - fitted
    ids = record.get("identities") if isinstance(record.get("identities"), dict) else {}
    by_id = {str(v): str(k) for k, v in ids.items()}
    spec = _spec(dataset) if dataset is not None else None
    here = dataset_identity(dataset, spec or {}) if dataset is not None else {"seal": None, "kind": None}
    rec_seal = (record.get("dataset") or {}).get("seal") if isinstance(record.get("dataset"), dict) else None
    trust = not ids or (rec_seal is not None and rec_seal == here["seal"])
    out_f, out_v, renamed = [], [], {}
    entries = sorted({str(e) for e in scored}, key=_name)
    known = identities(dataset, entries, here["kind"]) if ids else {}
    for e in entries:
        name = _name(e)
        ident = known.get(name)
        seen = by_id.get(ident) if ident is not None else None
        if seen is None and (trust or ident is None) and name in fitted | validation:
            seen = name
        if seen is None or seen not in fitted | validation:  # (an identity of a slide only held back: not seen)
            continue
        if seen != name:
            renamed[name] = seen
        (out_f if seen in fitted else out_v).append(name)
    return sorted(set(out_f)), sorted(set(out_v) - set(out_f)), renamed


def overlap(head, dataset, scored) -> tuple[list[str], list[str], str]:
    """``(fitted, validated, source)``: the names among ``scored`` (``dataset.json`` entries, paths or names) the head
    was fitted on, those it was validated on only (:func:`seen_among`), and :func:`slides_seen`'s source."""
    record, source = record_of(head_config(head), dataset)
    fitted, validated, _ = seen_among(record, dataset, scored)
    return fitted, validated, source


def check_scored(head, head_dir, dataset, scored, allow: bool = False, what: str = "scores") -> str | None:
    """Refuse (:class:`FittingSlidesError`, one line naming ``HEAD_DIR/config.json``) scoring ``scored`` slides with a
    head fitted or validated on some of them; with ``allow``, print the same as one ``warning:`` line on stderr and
    return it. ``None`` when no scored slide was seen in fitting. A head that records no slides and names a
    dataset that is not here: a warning that they cannot be checked (returned too)."""
    info = head_config(head)
    record, source = record_of(info, dataset)
    where = Path(head_dir) / "config.json" if head_dir is not None else None
    if source == "unknown":
        named = (info.get("fitted_on") or {}).get("dataset")
        line = (
            (f"{where}: " if where else "")
            + f"records no slides and was fitted on {named}, which is not here: which of the scored slides it saw cannot be checked"
        )
        print(f"warning: {line}", file=sys.stderr, flush=True)
        return None
    how = (
        ""
        if source == "recorded"
        else " (it records no slides: taken as fitted on this dataset's train split, as older heads were)"
    )
    return check_record(record, where, dataset, scored, allow, what, "head", how)


def check_record(
    record: dict | None,
    where,
    dataset,
    scored,
    allow: bool = False,
    what: str = "scores",
    who: str = "head",
    how: str = "",
) -> str | None:
    """The refusal of :func:`check_scored` for any :data:`RECORD` entry (a head's, or a policy's: a run's
    ``slides_seen.json``, :func:`run_record`); ``who`` names it in the line (``"head"``, ``"policy"``), ``where``
    the file that records it."""
    fitted, validated, renamed = seen_among(record, dataset, scored)
    if not fitted and not validated:
        return None
    seen = fitted + validated
    n = len({_name(e) for e in scored})
    verb = "fitted" if who == "head" else "trained"
    parts = ([f"{verb} on {len(fitted)}"] if fitted else []) + ([f"validated on {len(validated)}"] if validated else [])
    fold = (record or {}).get("fold")
    shown = [f"{s} (recorded as {renamed[s]})" if s in renamed else s for s in seen[:3]]
    on_fold = f"; it was {verb} on fold {fold}'s train side" if fold is not None else ""
    problem = (
        f"the {who} was {' and '.join(parts)} of the {n} slides it {what} (e.g. {', '.join(shown)})"
        f"{how}{on_fold}: figures on them are not held out"
    )
    if not allow:
        raise FittingSlidesError(
            where,
            f"{problem}; score slides it has not seen (the test split, or the held-out "
            f"fold of the {who} {verb} on that fold), or pass {FLAG} to score them with a "
            "warning",
        )
    line = f"{where}: {problem} ({FLAG} given)" if where else f"{problem} ({FLAG} given)"
    print(f"warning: {line}", file=sys.stderr, flush=True)
    return line


def seen_slides(record: dict | None, dataset, scored) -> list[str]:
    """The names among ``scored`` that ``record`` saw (fitted, trained or validated on: :func:`seen_among`), sorted:
    what a scorer writes as ``scored_on_seen_slides`` when :data:`FLAG` let it score them."""
    fitted, validated, _ = seen_among(record, dataset, scored)
    return sorted(fitted + validated)


def seen_mark(head, dataset, scored) -> dict:
    """What a scorer adds to the figures it writes (its JSON object; ``scored_on_seen_slides`` also as a CSV
    column) when :data:`FLAG` let ``head`` score slides it was fitted or validated on: ``{"self_scored": True,
    "scored_on_seen_slides": {"head": [names]}}``; ``{}`` when it saw none of ``scored``."""
    names = seen_slides(record_of(head_config(head), dataset)[0], dataset, scored)
    return {"self_scored": True, "scored_on_seen_slides": {"head": names}} if names else {}


def mark_words(mark: dict) -> str:
    """A :func:`seen_mark` as one CSV cell: ``"head: A B; policy: C"`` (``""`` for none)."""
    seen = mark.get("scored_on_seen_slides") or {}
    return "; ".join(f"{who}: {' '.join(names)}" for who, names in seen.items())


RUN_RECORD = "slides_seen.json"
"""The file of a training run's folder (and a published agent's) recording the slides it trained and validated on
(:func:`write_run_record`, the :data:`RECORD` entry of a head)."""


def validation_entries(spec: dict) -> list:
    """The validation slides a dataset holds back from its train split (``validation``: a list, as
    ``train_readers`` writes it, or :mod:`baselines.validation`'s record with its ``validation`` list)."""
    v = spec.get("validation")
    source = None
    if isinstance(v, dict):  # baselines.validation's record: entries of its source dataset
        source, v = v.get("source"), v.get("validation")
    if not isinstance(v, list):
        return []
    if isinstance(source, str) and source:
        return [str(Path(source) / str(e)) for e in v]
    return list(v)


def _env_kwargs(config) -> dict | None:
    """The ``env_kwargs`` of a run's config (typed, its dict, or its ``config.json`` / run folder: the run's own regular
    file, never a link or FIFO); None when it cannot be read or holds none that is an object. Read here, not through
    :mod:`baselines.run_config` (which imports the trainers, whose harness writes this record)."""
    if isinstance(config, (str, Path)):
        from baselines.harness.run_folder import MAX_CONFIG_BYTES, read_own

        path = Path(config)
        path = path / "config.json" if path.is_dir() else path
        try:
            config = json.loads(read_own(path, "config", MAX_CONFIG_BYTES))
        except (OSError, ValueError, HistojaxDataError):
            return None
    kw = config.get("env_kwargs") if isinstance(config, dict) else getattr(config, "env_kwargs", None)
    return dict(kw) if isinstance(kw, dict) else ({} if kw is None else None)


def run_slides(config) -> dict | None:
    """The :data:`RECORD` of a run trained on a dataset (``config``: its ``env_kwargs`` ``dataset``, ``split``,
    ``fold``): the dataset's seal and the names and identities of the side it trained on (``fitted``), and the
    validation slides its dataset holds back (``held_back``: scoring them is the validation that chooses among runs,
    so they are not refused; a published agent records those it was chosen on as ``validation``); None when it
    trained on no dataset (or one that cannot be read)."""
    from baselines.reading.slides import read_spec

    kw = _env_kwargs(config)
    if kw is None:
        return None
    dataset = kw.get("dataset")
    if not isinstance(dataset, str) or not dataset:
        return None
    try:
        spec = read_spec(dataset, kw.get("fold"))
    except (HistojaxDataError, OSError, ValueError):
        return None
    split = kw.get("split", "train")
    side = (spec.get("train") or []) + (spec.get("test") or []) if split == "all" else spec.get(split) or []
    # a fold's "validation" is its held-out side, not slides held back from training: none for a fold run
    held = validation_entries(spec) if kw.get("fold") is None else []
    record = fit_record(dataset, spec, kw.get("fold"), side, [], split=split)
    if held:  # scoring them is the validation that chooses the run: named, not refused (a chosen agent's are)
        record["held_back"] = sorted({_name(e) for e in held})
        both = identities(dataset, [*side, *held], record["dataset"]["kind"])
        record["identities"] = dict(sorted(both.items()))
    return record


def write_run_record(out, config) -> Path | None:
    """Write ``OUT/slides_seen.json`` (:data:`RUN_RECORD`: :func:`run_slides` of the run's ``config``); None, and
    nothing written, for a run on no dataset."""
    from baselines import outputs

    record = run_slides(config)
    if record is None:
        return None
    path = Path(out) / RUN_RECORD
    outputs.write_text(path, json.dumps(json_safe(record), indent=1, allow_nan=False) + "\n")
    return path


MAX_RECORD_BYTES = 64 << 20
"""A ``slides_seen.json`` larger than this (64 MiB; 180 slides take about 30 KB) is not read."""


def _read_run_record(path: Path) -> dict:
    """The JSON object of a run's ``slides_seen.json`` at ``path``: a regular file (a link to one is followed; a FIFO,
    folder or device is refused, never taken for no record, which would skip the guard), at most
    :data:`MAX_RECORD_BYTES`, whose ``fitted`` / ``validation`` / ``held_back`` are lists when present (entries that
    are not strings name no slide). ``HistojaxDataError`` naming it, one line, otherwise."""
    try:
        st = os.stat(path)
    except OSError as e:
        raise HistojaxDataError(path, f"unreadable ({e.strerror or e}); restore the record or train again") from None
    if not stat.S_ISREG(st.st_mode):
        raise HistojaxDataError(
            path, "not a regular file (a FIFO, folder or device): not the run's record of its slides"
        )
    if st.st_size > MAX_RECORD_BYTES:
        raise HistojaxDataError(
            path, f"{st.st_size:,} bytes, more than a record of slides holds ({MAX_RECORD_BYTES:,})"
        )
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | os.O_CLOEXEC)
        with os.fdopen(fd, "rb") as f:
            record = json.loads(f.read(MAX_RECORD_BYTES + 1))
    except (OSError, ValueError, RecursionError) as e:
        words = "nested too deeply" if isinstance(e, RecursionError) else f"{type(e).__name__}: {e}"
        raise HistojaxDataError(path, f"unreadable ({words})") from None
    if not isinstance(record, dict):
        raise HistojaxDataError(path, "not an object (fitted, validation, dataset, identities)")
    for key in ("fitted", "validation", "held_back"):
        if key in record and record[key] is not None and not isinstance(record[key], list):
            raise HistojaxDataError(path, f"its {key!r} is {type(record[key]).__name__}, not a list of slide names")
    return record


def run_record(run) -> tuple[dict | None, Path | None]:
    """``(record, file)``: the slides a run (or published agent) folder ``run`` trained and validated on, from its
    ``slides_seen.json``; else from what its ``config.json`` names (the dataset, split and fold, when that dataset
    is here: an older run); ``(None, None)`` when neither says (a run on one slide, a published folder without the
    record)."""
    run = Path(run)
    path = run / RUN_RECORD
    if os.path.lexists(path):
        return _read_run_record(path), path
    config = run / "config.json"
    if not config.is_file():
        return None, None
    try:
        record = run_slides(config)
    except HistojaxDataError:
        return None, None
    return (record, config) if record is not None else (None, None)


def check_policy(run, dataset, scored, allow: bool = False, what: str = "scores", option: str = "") -> list[str]:
    """The guard of every scorer of a trained policy (``histojax evaluate``, ``readers --reader``, ``budget-curve
    --ppo``, ``diagnosis --navigator``): :func:`check_record` of the run's record (:func:`run_record` of its folder;
    ``run`` may name its ``params.msgpack``) on the ``scored`` slides of ``dataset``, refused
    (:class:`FittingSlidesError`, one line naming ``RUN/slides_seen.json``) or, with ``allow``, warned about. Returns
    the names among ``scored`` it trained or was validated on (what :func:`with_seen` marks); ``[]`` for a run that
    records none (its ``held_back`` validation slides are not seen: scoring them is how runs are chosen).
    ``option`` (e.g. ``"--reader NAME"``): said first in the refusal, naming which of the scored policies it is."""
    folder = Path(run).parent if Path(run).is_file() else Path(run)  # RUN, or RUN/params.msgpack
    try:
        record, where = run_record(folder)
        if record is None:
            return []
        check_record(record, where, dataset, scored, allow, what, "policy")
    except HistojaxDataError as e:
        if not option:
            raise
        cls = FittingSlidesError if isinstance(e, FittingSlidesError) else HistojaxDataError
        raise cls(None, f"{option}: {e}") from None
    return seen_slides(record, dataset, scored)


def with_seen(mark: dict, who: str, names) -> dict:
    """``mark`` (:func:`seen_mark`, ``{}`` for none) with ``who``'s seen slide ``names`` added (``"policy NAME"``: a
    policy a scorer scored with :data:`FLAG` on slides it trained on, :func:`check_policy`); ``mark`` itself when
    ``names`` is empty."""
    if not names:
        return mark
    seen = {**(mark.get("scored_on_seen_slides") or {}), who: sorted(map(str, names))}
    return {"self_scored": True, "scored_on_seen_slides": seen}


def add_flag(p) -> None:
    """Add :data:`FLAG` to a scorer's argument parser."""
    p.add_argument(
        FLAG,
        dest="allow_fitting_slides",
        action="store_true",
        help="score slides the head (or a policy) was fitted, trained or validated on, with a warning (refused by "
        "default: figures on them are not held out)",
    )


def head_for_fold(head, fold: int) -> str:
    """The head folder of fold ``fold``: ``head`` with ``{fold}`` replaced, or ``HEAD/foldI`` when ``head`` is the
    folder ``learned_head_fit --all-folds`` wrote (``fold0``, ``fold1``, ... and no ``config.json``); else ``head``
    itself (one head for every fold: :func:`check_scored` refuses it where it saw a fold's slides)."""
    text = str(head)
    if "{fold}" in text:
        return text.replace("{fold}", str(fold))
    folder = Path(text)
    if not (folder / "config.json").exists():
        if (folder / f"fold{fold}" / "config.json").exists():
            return str(folder / f"fold{fold}")
        present = sorted(p.name for p in folder.glob("fold*") if (p / "config.json").is_file())
        if present:  # an --all-folds folder without this fold's head (e.g. a run that stopped early)
            raise HistojaxDataError(
                folder / f"fold{fold}",
                f"missing: {folder} holds the heads of {', '.join(present)} only; fit fold {fold}'s with "
                f"python -m baselines.reading.learned_head_fit --all-folds --out {folder} (or --fold {fold} --out "
                f"{folder / f'fold{fold}'})",
            )
    return text


__all__ = [
    "FLAG",
    "RECORD",
    "FittingSlidesError",
    "add_flag",
    "check_policy",
    "check_scored",
    "RUN_RECORD",
    "check_record",
    "dataset_identity",
    "fit_record",
    "identities",
    "mark_words",
    "record_of",
    "run_record",
    "run_slides",
    "seen_among",
    "seen_mark",
    "seen_slides",
    "slide_identity",
    "validation_entries",
    "with_seen",
    "write_run_record",
    "head_config",
    "head_for_fold",
    "overlap",
    "slides_seen",
]
