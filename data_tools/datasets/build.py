"""Build a dataset from a folder of real slides (``histojax dataset SLIDES_DIR --out DIR``).

Layout of ``DIR``: ``bundles/NAME/`` (one bundle per slide), ``records/NAME.json`` (a finished
slide: its settings, label, split, figures) and ``records/failed/NAME.json`` (its last failure, one-line
reason; a folder of its own, so no slide's record is another slide's failure record — before, failures were
``records/NAME.failed.json``, which the record of a slide named ``NAME.failed`` overwrote; such files are
still read), ``plan.json`` (the options and the cohort every shard must agree on),
``annotations/NAME.geojson`` (NCRF JSON converted) and, once every slide has a record, ``dataset.json``
(the split that ``histojax.make(..., dataset=DIR)`` loads, the labels, the failures; sealed with its
digest, so a ``dataset.json`` histojax did not write is never overwritten).

Nothing of the user's is deleted: a slide is built into a hidden ``bundles/.NAME.tmp-*`` and swapped into
place only once whole, so a failed rebuild leaves the previous bundle (and its record) as they were; a
``bundles/NAME`` holding files histojax did not write is neither replaced nor removed (the slide fails,
naming them).

Restartable: a slide whose record matches its settings and whose bundle is there is not built
again; a killed run's temporaries are removed (:func:`data_tools.datasets.locks.clean_stale`).
Parallel: ``jobs`` processes on one machine; ``shard=(I, N)`` builds every N-th of the sorted slide
names starting at the I-th, so N machines sharing ``DIR`` build disjoint sets; each bundle is built
holding its own lock, so two processes never build one bundle. The run that finds every slide
recorded (or :func:`merge_dataset`) writes ``dataset.json``. A slide that fails is recorded with its
reason and the others still build.
"""

from __future__ import annotations

import functools
import json
import os
import resource
import shutil
import time
import uuid
import warnings
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from data_tools.bundle_files.reading import bundle_damage, read_metadata
from data_tools.bundle_files.seals import DATASET_DIGEST, SEALING_KINDS, metadata_digest
from data_tools.bundle_files.writes import foreign_entries, mark_temporary, replace_folder, write_json
from data_tools.datasets.locks import (
    RUN_LOCK,
    LockHeld,
    RunLock,
    bundle_lock_path,
    clean_partial_features,
    clean_stale,
    file_lock,
)
from data_tools.datasets.split import (
    fold_lists,
    folds_record,
    kfold_split,
    patient_groups,
    patients_on_both_sides,
    read_patient_column,
    seeded_split,
    shard_names,
)
from data_tools.errors import HistojaxDataError
from data_tools.features.encoders import dataset_scale

KIND = "histojax dataset of real slides (data_tools dataset)"
MPP_TOLERANCE = 0.05  # relative: slides within 5 % µm/px share one --magnification-range


def _fingerprint(path: Path) -> dict:
    """Cheap identity of a slide file or DICOM folder: size in bytes and mtime (ns) of its files. A MIRAX ``.mrxs``
    counts every file of its data folder too (``Slidedat.ini``, ``Index.dat``, ``Data*.dat``:
    :func:`~data_tools.slide_files.mirax.slide_files`), so a slide whose pixels changed is rebuilt, not "already
    done"."""
    from data_tools.slide_files.mirax import slide_files

    if path.is_dir():
        files = sorted(path.rglob("*"))
    elif path.suffix.lower() == ".mrxs":
        files = slide_files(path)
    else:
        files = [path]
    stats = [f.stat() for f in files if f.is_file()]
    return {
        "bytes": int(sum(s.st_size for s in stats)),
        "mtime_ns": int(max((s.st_mtime_ns for s in stats), default=0)),
    }


def _rel(path: Path, root: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(Path(root).resolve()))
    except ValueError:
        return str(Path(path).resolve())


def check_scales(
    entries, magnification_range, reader: str | None = None, mpp: float | None = None
) -> dict[str, float | None]:
    """µm/px of every slide (``mpp``: the one given for all, ``--mpp``, instead of what the files state); with one
    ``magnification_range`` for all, slides whose level-0 µm/px differ by more than 5 % (or some unknown) are an
    error naming two of them: one range would give them different physical scales."""
    from data_tools.slide_files.open import open_slide

    mpps: dict[str, float | None] = {}
    for e in [] if mpp is not None else entries:
        try:
            with open_slide(e.path, reader) as slide:
                mpps[e.name] = slide.mpp
        except HistojaxDataError:
            mpps[e.name] = None  # unreadable: fails (with its reason) when built
        except Exception:  # noqa: BLE001 - any reader trouble shows up again, as a one-line failure, when built
            mpps[e.name] = None
    if mpp is not None:
        mpps = {e.name: float(mpp) for e in entries}
    if magnification_range is not None:
        known = {n: m for n, m in mpps.items() if m}
        unknown = [e for e in entries if not mpps.get(e.name)]
        if known and unknown:
            raise HistojaxDataError(
                unknown[0].path,
                f"has no µm/px while {next(iter(known))} has "
                f"{next(iter(known.values())):.4g}: one --magnification-range "
                f"{magnification_range:g} would mix scales; build them in separate datasets",
            )
        if known:
            lo, hi = min(known, key=known.get), max(known, key=known.get)
            if known[hi] > known[lo] * (1 + MPP_TOLERANCE):
                raise HistojaxDataError(
                    next(e.path for e in entries if e.name == hi),
                    f"is {known[hi]:.4g} µm/px but {lo} is {known[lo]:.4g} µm/px: one "
                    f"--magnification-range {magnification_range:g} would give their levels "
                    "different physical scales; omit it (each slide its own range) or build "
                    "them in separate datasets",
                )
    return mpps


def make_plan(
    entries,
    slides_dir,
    options: dict,
    test_fraction: float,
    seed: int,
    folds: int | None = None,
    patients: dict[str, str] | None = None,
) -> dict:
    """The cohort and options every shard must agree on: slide → (path relative to ``slides_dir``,
    annotation, label, split); with ``folds`` (K), ``folds``: K folds stratified by label, the slides of one
    patient (``patients``: name → patient from the label table, else a TCGA barcode's) in one fold, over every
    slide when the split is seeded, over the train side when it is given (see
    :func:`data_tools.datasets.split.kfold_split`)."""
    fixed = {e.name: e.split for e in entries if e.split}
    if fixed and len(fixed) != len(entries):
        loose = [e.name for e in entries if not e.split]
        raise HistojaxDataError(loose[0], f"{len(loose)} slide(s) have no split while others do (e.g. {loose[:3]})")
    every, grouped_by = patient_groups([e.name for e in entries], patients)
    several = len(set(every.values())) < len(every)  # some patient has two slides or more
    if fixed:
        split = fixed
        rule = "given (CAMELYON16 official split or the label table's split column)"
        for patient, sides in patients_on_both_sides(split, every).items():
            where = "; ".join(f"{side}: {', '.join(names)}" for side, names in sorted(sides.items()))
            warnings.warn(
                f"the given split puts patient {patient} on both sides ({where}): its figures on the test "
                "side are not patient-held-out; move the patient's slides to one side",
                stacklevel=2,
            )
    else:
        train, test = seeded_split(
            [e.name for e in entries],
            {e.name: e.label for e in entries},
            test_fraction,
            seed,
            every if several else None,
        )  # one slide each: the split it always had
        split = {**{n: "train" for n in train}, **{n: "test" for n in test}}
        rule = f"seeded (seed {seed}), stratified by label, {test_fraction:.0%} of each label in test"
        if several:  # a cohort of one slide per patient keeps the rule (and the split) it always had
            rule += f", the slides of one patient on one side ({grouped_by})"
    slides = {
        e.name: {
            "path": _rel(e.path, slides_dir),
            "annotation": None if e.annotation is None else _rel(e.annotation, slides_dir),
            "annotation_kind": e.annotation_kind,
            "label": int(e.label),
            "label_source": e.label_source,
            "split": split[e.name],
        }
        for e in entries
    }
    plan = {"kind": KIND, "options": options, "split_rule": rule, "slides": slides}
    plan["split_grouped_by"] = grouped_by  # a plan written before it (no such key) is still agreed to: _agree
    if several:  # slide -> patient, for the validation shares cut from the train side (baselines.validation.units)
        plan["patients"] = {n: g.split(":", 1)[1] for n, g in sorted(every.items()) if g.startswith("patient:")}
    if folds is not None:
        pool = [n for n in slides if not fixed or split[n] == "train"]
        groups, grouped_by = patient_groups(pool, patients)
        fold = kfold_split(pool, {n: slides[n]["label"] for n in pool}, folds, seed, groups)
        plan["folds"] = folds_record(fold, folds, seed, "train" if fixed else "all", grouped_by)
    return plan


def read_plan(out) -> dict:
    """``OUT/plan.json`` of a ``histojax dataset`` build, checked: a JSON object of this tool's kind with an
    ``options`` record and a ``slides`` record of slide records. Anything else (absent, malformed, another
    tool's ``plan.json``) is a ``HistojaxDataError`` naming the file."""
    import stat

    from data_tools.bundle_files.safe_files import not_regular
    from data_tools.bundle_files.seals import MAX_DATASET_JSON_BYTES

    path = Path(out) / "plan.json"
    try:
        st = os.stat(path)  # a link to a regular file is read, as before
        if not stat.S_ISREG(st.st_mode) or st.st_size > MAX_DATASET_JSON_BYTES:
            what = f"{st.st_size:,} bytes" if stat.S_ISREG(st.st_mode) else not_regular(st)
            raise HistojaxDataError(  # a FIFO would block the read for ever
                path, f"is {what}, not a histojax dataset plan; refusing to touch it: choose another --out"
            )
        with os.fdopen(os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0)), "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise HistojaxDataError(path, "changed while it was opened (not a regular file now); refusing it")
            plan = json.loads(f.read(MAX_DATASET_JSON_BYTES + 1).decode("utf-8"))
    except FileNotFoundError:
        raise HistojaxDataError(out, "no plan.json: not a dataset started by `histojax dataset`") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as e:  # RecursionError: nested
        # deeper than the parser recurses
        raise HistojaxDataError(
            path,
            f"unreadable ({_one_line(e)}); not a histojax dataset plan, refusing to touch it: choose another --out",
        ) from None
    slides = plan.get("slides") if isinstance(plan, dict) else None
    if (
        not isinstance(plan, dict)
        or plan.get("kind") != KIND
        or not isinstance(plan.get("options"), dict)
        or not isinstance(slides, dict)
        or not all(isinstance(v, dict) and {"split", "label", "path"} <= set(v) for v in slides.values())
    ):
        found = (
            f"kind {plan.get('kind')!r}"
            if isinstance(plan, dict) and "kind" in plan
            else f"slides {type(slides).__name__}"
            if isinstance(plan, dict)
            else type(plan).__name__
        )
        raise HistojaxDataError(
            path,
            f"is not a histojax dataset plan ({found}; another tool's file?); "
            "refusing to touch it: choose another --out",
        )
    return plan


def _check_out_apart(slides_dir: Path, out: Path) -> None:
    """Refuse (one line) an ``--out`` that is the folder of slides itself or holds it: discovery leaves ``--out``
    out, so every slide would be passed over ("holds no slides")."""
    src, dst = Path(slides_dir).resolve(), Path(out).resolve()
    if src == dst or dst in src.parents:
        where = "is the folder of slides itself" if src == dst else f"holds the folder of slides {slides_dir}"
        raise HistojaxDataError(
            out,
            f"--out {where}: the dataset (bundles, records, dataset.json) needs a folder "
            f"of its own, e.g. --out {src.name}-dataset beside it",
        )


PLAN_PARTS = {
    "options": "other options",
    "slides": "another cohort of slides",
    "split_rule": "another split rule",
    "folds": "other folds (or none)",
    "patients": "other patients (the label table's patient column)",
}
"""How a refusal names each part of ``plan.json`` that differs from the command's."""


def _agree(out: Path, plan: dict, restart: bool = False) -> None:
    """Write ``plan.json`` if absent (or, with ``restart``, over this tool's own plan); else refuse a run whose
    options or cohort differ (one line). A ``plan.json`` this tool did not write is never touched."""
    path = out / "plan.json"
    if path.exists() or path.is_symlink():
        old = read_plan(out)
        if "split_grouped_by" not in old:  # written before splits were grouped by patient: the same split agrees
            old = {**old, "split_grouped_by": plan.get("split_grouped_by")}
        if "patients" not in old and "patients" in plan:  # written before the patients were recorded: the same
            old = {**old, "patients": plan["patients"]}  # labels and names give the same patients
        if not restart and old != plan and plan.get("folds") and {**old, "folds": plan["folds"]} == plan:
            # only the folds are new: they depend on the labels and patients alone, so no bundle is rebuilt
            print(
                f"{path}: the folds are new ({plan['folds'].get('k', '?')} folds); every bundle is kept and "
                "dataset.json is written again with them",
                flush=True,
            )
        elif not restart and old != plan:
            what = [PLAN_PARTS[k] for k in PLAN_PARTS if old.get(k) != plan.get(k)]
            detail = ""
            if old.get("options") != plan.get("options"):
                diff = sorted(
                    k
                    for k in set(old["options"]) | set(plan["options"])
                    if old["options"].get(k) != plan["options"].get(k)
                )
                detail = f" (options {diff})"
            elif old.get("slides") != plan.get("slides"):
                diff = sorted(
                    k for k in set(old["slides"]) | set(plan["slides"]) if old["slides"].get(k) != plan["slides"].get(k)
                )
                detail = f" (slides {diff[:4]})"
            raise HistojaxDataError(
                path,
                f"this dataset was started with {' and '.join(what)}{detail}; "
                "use the same command, a new --out, or --restart",
            )
    write_json(path, plan)


def _settings_key(name: str, slide: dict, options: dict, slides_dir: Path) -> dict:
    return {
        "slide": slide,
        "options": options,
        "fingerprint": _fingerprint(slides_dir / slide["path"]),
        "annotation_fingerprint": None
        if slide["annotation"] is None
        else _fingerprint(slides_dir / slide["annotation"]),
    }


def record_path(out: Path, name: str, failed: bool = False) -> Path:
    """``OUT/records/NAME.json`` (a finished slide) or ``OUT/records/failed/NAME.json`` (its failure): slide
    names hold no ``/``, so the two never collide, whatever the names."""
    folder = Path(out) / "records" / ("failed" if failed else "")
    folder.mkdir(parents=True, exist_ok=True)
    return folder / f"{name}.json"


def _legacy_failed_path(out: Path, name: str) -> Path:
    """Where failures were recorded before ``records/failed/`` (``records/NAME.failed.json``)."""
    return Path(out) / "records" / f"{name}.failed.json"


def _read_json(path: Path) -> dict | None:
    try:
        rec = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    return rec if isinstance(rec, dict) else None


def read_record(out: Path, name: str, failed: bool = False) -> dict | None:
    """The record (or failure record) of slide ``name`` in the dataset ``out``; None when absent, unreadable or
    another slide's (a record names its slide). Failure records of older builds (``records/NAME.failed.json``)
    are read when they name this slide."""
    rec = _read_json(record_path(out, name, failed))
    if rec is None and failed:
        rec = _read_json(_legacy_failed_path(out, name))
        if rec is not None and "reason" not in rec:
            rec = None
    if rec is not None and "name" in rec and rec["name"] != name:
        return None
    return rec


def _clear_failed(out: Path, name: str) -> None:
    """Remove slide ``name``'s failure record (and an older build's ``records/NAME.failed.json`` naming it)."""
    record_path(out, name, failed=True).unlink(missing_ok=True)
    legacy = _legacy_failed_path(out, name)
    old = _read_json(legacy)
    if old is not None and old.get("name") == name and "reason" in old:
        legacy.unlink(missing_ok=True)


def check_bundle_folder(bundle: Path) -> None:
    """Refuse (``HistojaxDataError`` naming the folder and a file) a ``bundles/NAME`` that is not absent, empty
    or a bundle histojax wrote (:func:`data_tools.bundle_files.writes.foreign_entries`): a folder of the user's files
    inside ``--out`` is never replaced nor removed."""
    if not (bundle.exists() or bundle.is_symlink()):
        return
    if bundle.is_symlink() or not bundle.is_dir():
        raise HistojaxDataError(
            bundle,
            "is not a bundle folder (a file or a link); refusing to replace it: move it away or choose another --out",
        )
    foreign = foreign_entries(bundle)
    if foreign:
        raise HistojaxDataError(
            bundle,
            f"holds {len(foreign)} file(s) histojax did not write (e.g. {foreign[0]!r}); "
            "refusing to replace or remove them: move them away or choose another --out",
        )


BUILD_ERRORS = (HistojaxDataError, OSError, ValueError, MemoryError)
"""What a slide's build may raise that is the slide's fault: recorded, and the cohort goes on."""


def run_locked(out, name: str, work, current=None, staged: bool = False) -> dict:
    """Build slide ``name`` of the dataset ``out`` holding its bundle's lock (``bundles/.NAME.dataset-lock``,
    not blocking: a slide another process or shard is building is reported ``busy`` and skipped).
    ``current(record) -> bool``: a record that needs no rebuild (``resumed``; default: always rebuild).
    A ``bundles/NAME`` holding files histojax did not write fails the slide at once, untouched
    (:func:`check_bundle_folder`). ``staged``: ``work(folder) -> record`` builds the bundle into the hidden
    ``bundles/.NAME.tmp-*`` given, swapped onto ``bundles/NAME`` once whole
    (:func:`data_tools.bundle_files.writes.replace_folder`); a build error (:data:`BUILD_ERRORS`) removes only
    that temporary, so a previous bundle and its record stay as they were. Not ``staged``:
    ``work() -> record`` builds ``bundles/NAME`` in place and a build error removes it (only when histojax
    wrote every file in it). The record goes to ``records/NAME.json``, a failure to
    ``records/failed/NAME.json`` with its one-line reason. A current record resumes only while its bundle is
    whole (:func:`data_tools.bundle_files.reading.bundle_damage`: every checksum checked); a damaged one is built again.
    Returns ``{"name", "status": "built" | "resumed" | "failed" | "busy", "reason"?, "record"?, "kept"?,
    "damaged"?}`` (``kept``: a failed rebuild left the previous bundle; ``damaged``: why a finished bundle was
    built again).
    The one per-slide step of ``data_tools dataset`` and ``data_tools c16``."""
    out = Path(out)
    bundle = out / "bundles" / name
    t0 = time.perf_counter()
    try:
        lock = file_lock(bundle_lock_path(bundle), blocking=False, what=f"bundle {name}")
        lock.__enter__()
    except LockHeld:
        return {"name": name, "status": "busy"}

    tmp = bundle.parent / f".{name}.tmp-{uuid.uuid4().hex[:8]}"  # where a staged build writes

    def failed(e: BaseException) -> dict:
        reason = (
            _one_line(e)
            if not (isinstance(e, OSError) and e.filename is None)
            else f"{bundle}: {_one_line(e.strerror or e)}"
        )
        reason = reason.replace(str(tmp), str(bundle))  # name the bundle, not its hidden temporary
        kept = staged and read_record(out, name) is not None and (bundle / "metadata.json").is_file()
        write_json(record_path(out, name, failed=True), {"name": name, "reason": reason, "previous_kept": kept})
        return {"name": name, "status": "failed", "reason": reason, "kept": kept}

    try:
        rec = read_record(out, name)
        damage = None
        if rec is not None and current is not None and current(rec) and (bundle / "metadata.json").is_file():
            damage = bundle_damage(bundle)  # a bundle changed since (a flipped byte, a file gone) is built again
            if damage is None:
                clean_partial_features(bundle)
                return {"name": name, "status": "resumed", "record": rec}
        try:
            check_bundle_folder(bundle)
        except HistojaxDataError as e:
            return failed(e)
        if staged:
            try:
                mark_temporary(tmp)  # proof for the next run's cleaning that this folder is histojax's
                rec = work(tmp)
                check_bundle_folder(bundle)  # again: files may have been put there meanwhile
                replace_folder(tmp, bundle)
            except BUILD_ERRORS as e:
                shutil.rmtree(tmp, ignore_errors=True)
                return failed(e)
            except BaseException:
                shutil.rmtree(tmp, ignore_errors=True)
                raise
        else:
            record_path(out, name).unlink(missing_ok=True)
            try:
                rec = work()
            except BUILD_ERRORS as e:
                if bundle.is_dir() and not bundle.is_symlink() and not foreign_entries(bundle):
                    shutil.rmtree(bundle, ignore_errors=True)  # half a bundle, every file histojax's
                return failed(e)
        rec.setdefault("seconds", round(time.perf_counter() - t0, 2))
        rec.setdefault("peak_rss_bytes", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
        write_json(record_path(out, name), rec)
        _clear_failed(out, name)
        return {"name": name, "status": "built", "record": rec, **({"damaged": damage} if damage else {})}
    finally:
        lock.__exit__(None, None, None)


def run_summary(results: list[dict]) -> dict:
    """This run's slides by the status :func:`run_locked` gave them: ``built`` / ``resumed`` / ``busy`` names
    and ``failed`` (name → reason)."""
    return {
        **{k: [r["name"] for r in results if r["status"] == k] for k in ("built", "resumed", "busy")},
        "failed": {r["name"]: r["reason"] for r in results if r["status"] == "failed"},
        "kept": [r["name"] for r in results if r["status"] == "failed" and r.get("kept")],
    }


def collect_records(out, names, current=None) -> tuple[dict[str, dict], dict[str, str], list[str]]:
    """The finished slides among ``names`` of the dataset ``out``: ``(records, failed, missing)`` —
    name → record (without its ``settings``) for each slide with a record (``current(record)`` true,
    when given) and a bundle; name → reason for each recorded failure; the names with neither (still to
    build, by this run or another shard). The one reader of records for ``merge`` and ``c16``."""
    out = Path(out)
    records, failed, missing = {}, {}, []
    for name in names:
        rec = read_record(out, name)
        if (
            rec is not None
            and (current is None or current(rec))
            and (out / "bundles" / name / "metadata.json").is_file()
        ):
            records[name] = {k: v for k, v in rec.items() if k != "settings"}
            continue
        bad = read_record(out, name, failed=True)
        if bad is not None and "reason" in bad:
            failed[name] = str(bad["reason"])
        else:
            missing.append(name)
    return records, failed, missing


def h5_index(features_from) -> dict[str, Path]:
    """``NAME.h5`` files under ``features_from`` (CLAM ``h5_files/``, TRIDENT ``features_*/``), keyed by
    lower-cased name; two files of one name are an error naming both."""
    folder = Path(features_from)
    if not folder.is_dir():
        raise HistojaxDataError(folder, "no such folder of .h5 feature files")
    from data_tools.datasets.discover import by_name

    return by_name(sorted(folder.rglob("*.h5")), "feature files", "point --features-from at one encoder's folder")


def build_one(job: dict) -> dict:
    """Build one slide's bundle (unless its record is current) through :func:`run_locked`; returns
    ``{"name", "status": "built" | "resumed" | "failed" | "busy", "reason"?, "record"?}``."""
    out, name, slide, opts = Path(job["out"]), job["name"], job["slide"], job["options"]
    slides_dir = Path(job["slides_dir"])
    key = _settings_key(name, slide, opts, slides_dir)
    return run_locked(
        out,
        name,
        lambda folder: _build(
            out, name, slide, opts, slides_dir, folder, key, job.get("h5"), job.get("progress", False)
        ),
        current=lambda rec: rec.get("settings") == key,
        staged=True,
    )


def _one_line(e: BaseException) -> str:
    from data_tools.cli_output import one_line, os_error_text

    return one_line(os_error_text(e) if isinstance(e, OSError) else str(e) or type(e).__name__)


def _build(out, name, slide, opts, slides_dir, bundle, key, h5, progress) -> dict:
    """The work of :func:`build_one` (lock held): the bundle is built into ``bundle`` (a temporary folder)."""
    import warnings

    from data_tools.bundle import build_bundle

    path = slides_dir / slide["path"]
    ann = None if slide["annotation"] is None else slides_dir / slide["annotation"]
    if ann is not None and slide["annotation_kind"] == "ncrf":
        from data_tools.datasets.discover import ncrf_to_geojson

        ann = ncrf_to_geojson(ann, out / "annotations" / f"{name}.geojson")
    if opts["features_from"] and h5 is None:
        raise HistojaxDataError(path, f"no feature file {name}.h5 in --features-from {opts['features_from']}")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        build_bundle(
            path,
            bundle,
            annotations_path=ann,
            level_sets=opts["levels"],
            tile_size=opts["tile_size"],
            magnification_range=opts["magnification_range"],
            storage=opts["storage"],
            overwrite=True,
            progress=progress,
            label_map=opts["label_map"],
            reader=opts.get("reader"),
            mpp=opts.get("mpp"),
        )
    notes = sorted({_one_line(w.message) for w in caught})
    meta = read_metadata(bundle)
    tissue = np.load(bundle / meta.tissue_file, allow_pickle=False)
    if not tissue.any():
        raise HistojaxDataError(path, "no tissue found (the coarsest level is blank glass): not a usable slide")
    tumour_px = float((meta.annotations or {}).get("tumour_area_px") or 0.0)
    if slide["label"] == 1 and slide["label_source"].startswith("annotated") and tumour_px <= 0:
        raise HistojaxDataError(
            ann,
            "annotation has no tumour polygon (groups map to "
            f"{(meta.annotations or {}).get('n_polygons')}); label the slide in --labels or "
            "fix --label-map",
        )
    if slide["label"] == 0 and tumour_px > 0:
        raise HistojaxDataError(
            ann, f"marks {tumour_px:.0f} px² of tumour but the slide is labelled normal ({slide['label_source']})"
        )
    if h5 is not None:
        from data_tools.features.hdf5 import import_features

        import_features(bundle, h5, patch_size=opts["patch_size"], level=opts["patch_level"])
    elif opts["encoder"]:
        from data_tools.features.grid import compute_features

        compute_features(bundle, encoder_name=opts["encoder"], progress=progress, verify=False)
    clean_partial_features(bundle)
    if opts["no_pixels"]:
        from data_tools.bundle import drop_pixels

        drop_pixels(bundle)
    meta = read_metadata(bundle)
    return {
        "name": name,
        "bundle": f"bundles/{name}",
        "source": slide["path"],
        "label": slide["label"],
        "label_source": slide["label_source"],
        "split": slide["split"],
        "settings": key,
        "format": meta.source.get("format"),
        "width": meta.source.get("width"),
        "height": meta.source.get("height"),
        "mpp": meta.source.get("mpp"),
        "storage": meta.storage,
        "tumour_area_level0_px2": tumour_px,
        "encoder": (meta.features or {}).get("encoder"),
        "pixels_kept": len(meta.pixel_levels) == len(meta.levels),
        "bundle_bytes": sum(f.stat().st_size for f in bundle.rglob("*") if f.is_file()),
        "device_bytes_pixels": meta.device_bytes,
        "notes": notes,
    }


def write_dataset_json(out, plan: dict, records: dict[str, dict], failed: dict[str, str], extra=None) -> dict:
    """Write ``OUT/dataset.json`` (atomically, holding ``OUT/.dataset.lock``): ``train`` / ``test`` lists of
    the built bundles (``bundles/NAME``) by the plan's split, ``labels`` (name → 0/1), ``slides`` (the
    records), ``failed`` (name → reason). Returns it."""
    out = Path(out)
    names = sorted(records)
    dataset = {
        "kind": plan.get("kind", KIND),
        "split_rule": plan.get("split_rule"),
        "split_grouped_by": plan.get("split_grouped_by", "one slide per patient (built before patient grouping)"),
        "options": plan.get("options"),
        "encoder": _encoder_of(plan.get("options") or {}),
        "train": [f"bundles/{n}" for n in names if plan["slides"][n]["split"] == "train"],
        "test": [f"bundles/{n}" for n in names if plan["slides"][n]["split"] == "test"],
        "labels": {n: int(plan["slides"][n]["label"]) for n in names},
        "failed": dict(sorted(failed.items())),
        "slides": [records[n] for n in names],
        **({"folds": fold_lists(plan["folds"], names)} if plan.get("folds") else {}),
        **({"patients": {n: p for n, p in plan["patients"].items() if n in records}} if plan.get("patients") else {}),
        **(extra or {}),
    }
    scale, _ = dataset_scale(dataset["encoder"], {n: plan["slides"][n].get("mpp") for n in names})
    if scale is not None:  # a built-in encoder's scale against the slides' (warned when the plan was made)
        dataset["encoder_scale"] = scale
    return write_dataset_index(out, dataset)


def _encoder_of(options: dict) -> str | None:
    """The feature grids' encoder, as the ids' ``dataset_encoder`` checks it: ``--encoder``'s name, ``"imported"``
    for ``--features-from``, None without features."""
    from data_tools.features import encoder_name  # your own encoder (module:function): the name it records

    return encoder_name(options.get("encoder")) or ("imported" if options.get("features_from") else None)


def dataset_json_is_ours(path) -> bool:
    """True when ``path`` (a ``dataset.json``) is absent or provably written by histojax: sealed with a digest
    that matches, or (written before the seal) a JSON object of a histojax kind with ``train`` / ``test``
    lists, ``labels`` and ``slides``. A file a user wrote (``{}``) or edited since is not."""
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        return True
    if path.is_symlink() or not path.is_file():
        return False
    old = _read_json(path)
    if old is None:
        return False
    if DATASET_DIGEST in old:
        return old[DATASET_DIGEST] == metadata_digest({k: v for k, v in old.items() if k != DATASET_DIGEST})
    return (
        old.get("kind") in SEALING_KINDS
        and isinstance(old.get("train"), list)
        and isinstance(old.get("test"), list)
        and isinstance(old.get("labels"), dict)
        and isinstance(old.get("slides"), list)
    )


def check_dataset_json(out) -> None:
    """Refuse (one line naming the file) an ``OUT/dataset.json`` histojax cannot prove it wrote
    (:func:`dataset_json_is_ours`): it is never overwritten."""
    path = Path(out) / "dataset.json"
    if not dataset_json_is_ours(path):
        raise HistojaxDataError(
            path,
            "was not written by histojax dataset or c16 (or was edited since); refusing to "
            "overwrite it: move it away or choose another --out",
        )


def write_dataset_index(out, dataset: dict) -> dict:
    """Write ``dataset`` as ``OUT/dataset.json`` atomically, holding ``OUT/.dataset.lock``, sealed with its digest
    (:data:`DATASET_DIGEST`), over nothing but a ``dataset.json`` histojax wrote (:func:`check_dataset_json`);
    the one writer of ``dataset.json`` for ``data_tools dataset`` and ``c16``. Returns it (sealed)."""
    out = Path(out)
    body = {k: v for k, v in dataset.items() if k != DATASET_DIGEST}
    dataset = {**body, DATASET_DIGEST: metadata_digest(body)}
    with file_lock(out / ".dataset.lock", what=str(out)):
        check_dataset_json(out)
        write_json(out / "dataset.json", dataset)
    return dataset


def check_scorable(out, plan: dict, records: dict, failed: dict[str, str]) -> None:
    """Refuse (``HistojaxDataError``, one line) a test split that failed slides left unscorable: the plan gave
    it slides and it now holds none, or the plan gave it tumour slides and it now holds no tumour slide. (An
    empty train side is reported by the command, not refused: the test slides may still be scored.)"""
    for side in ("test",):
        planned = sorted(n for n, s in plan["slides"].items() if s["split"] == side)
        built = [n for n in planned if n in records]
        lost = [n for n in planned if n not in records]
        why = "; ".join(f"{n}: {failed[n]}" for n in lost[:2] if n in failed)[:300]
        if planned and not built:
            raise HistojaxDataError(
                out,
                f"the {side} split would hold no slide: all {len(planned)} of its slides "
                f"failed ({why}); dataset.json not written (built slides are kept): fix "
                "them and rerun",
            )
        tumour = [n for n in planned if int(plan["slides"][n]["label"]) == 1]
        if tumour and not any(n in records for n in tumour):
            why = "; ".join(f"{n}: {failed[n]}" for n in tumour[:2] if n in failed)[:300]
            raise HistojaxDataError(
                out,
                f"the {side} split would hold no tumour slide: its {len(tumour)} tumour "
                f"slide(s) failed ({why}), so it cannot be scored; dataset.json not "
                "written (built slides are kept): fix them and rerun",
            )


def merge_dataset(out) -> tuple[dict | None, list[str], dict[str, str]]:
    """Read ``OUT/plan.json`` (:func:`read_plan`) and every record; write ``dataset.json`` when every slide has
    one, unless failures left the test split unscorable (:func:`check_scorable` raises; nothing written). A
    slide counts as built when its record was made with the plan's options and entry (so a previous bundle
    kept by a failed rebuild counts only when nothing but the slide file changed; it is then listed under
    ``kept_after_failed_rebuild`` with the reason). Returns ``(dataset or None, names still missing, failed
    name → reason)``."""
    out = Path(out)
    plan = read_plan(out)

    def usable(rec) -> bool:  # built for this plan (a previous bundle kept by a failed rebuild may not be)
        settings, name = rec.get("settings"), rec.get("name")
        if not isinstance(settings, dict) or name not in plan["slides"]:
            return False
        return settings.get("options") == plan["options"] and settings.get("slide") == plan["slides"][name]

    records, failed, missing = collect_records(out, sorted(plan["slides"]), current=usable)
    if missing:
        return None, missing, failed
    kept = {}
    for name in records:
        bad = read_record(out, name, failed=True)
        if bad is not None and "reason" in bad:
            kept[name] = str(bad["reason"])
    check_scorable(out, plan, records, failed)
    if plan["slides"] and not records:  # every slide failed (none planned for test): no dataset of 0 slides
        why = "; ".join(f"{n}: {failed[n]}" for n in sorted(failed)[:2])[:300]
        raise HistojaxDataError(
            out,
            f"no slide of this dataset is built: all {len(plan['slides'])} failed ({why}); "
            "dataset.json not written: fix them and rerun",
        )
    extra = {"kept_after_failed_rebuild": kept} if kept else None
    return write_dataset_json(out, plan, records, failed, extra), [], failed


_HELD: list = []
"""The :class:`data_tools.datasets.locks.RunLock` of each :func:`build_dataset` call in progress (innermost last)."""


def _hold_run(out: Path, plan: dict) -> None:
    """Take ``OUT/.dataset-run.lock`` for this run (call holding ``OUT/.dataset.lock``): shared when ``plan.json``
    already holds this plan, exclusive when this run would write another; refused (``HistojaxDataError``, one
    line) while a run of other options holds the folder. Released when :func:`build_dataset` returns."""
    same = False
    if (out / "plan.json").is_file():
        try:
            same = read_plan(out) == plan
        except HistojaxDataError:
            same = False
    run = RunLock(out / RUN_LOCK)
    if not run.claim(exclusive=not same):
        raise HistojaxDataError(
            out,
            "another histojax dataset run is building this folder with other options "
            "(or another cohort); wait for it to finish (or stop it), then rerun, or "
            "choose another --out",
        )
    _HELD.append(run)


def _releasing_run_lock(build):
    """Release the run locks :func:`build_dataset` took (:func:`_hold_run`) however it ends."""

    @functools.wraps(build)
    def wrapper(*args, **kwargs):
        depth = len(_HELD)
        try:
            return build(*args, **kwargs)
        finally:
            while len(_HELD) > depth:
                _HELD.pop().release()

    return wrapper


@_releasing_run_lock
def build_dataset(
    slides_dir,
    out,
    *,
    labels=None,
    annotations=None,
    levels=(3, 5, 7),
    tile_size: int = 128,
    magnification_range: float | None = None,
    storage: str = "auto",
    label_map=None,
    encoder: str | None = None,
    features_from=None,
    patch_size: int | None = None,
    patch_level: int | None = None,
    no_pixels: bool = False,
    test_fraction: float = 0.25,
    seed: int = 0,
    jobs: int = 1,
    shard: tuple[int, int] | None = None,
    restart: bool = False,
    allow_unmatched: bool = False,
    progress: bool = True,
    reader: str | None = None,
    folds: int | None = None,
    mpp: float | None = None,
) -> dict:
    """Build (or finish) the dataset ``out`` from the slides under ``slides_dir`` (see the module doc and
    :mod:`data_tools.datasets.discover`). ``levels`` / ``tile_size`` (px) / ``magnification_range`` (the
    coarsest downsample; default each slide's own) / ``storage`` / ``label_map``: as ``build``.
    ``encoder``: compute each bundle's feature grid; ``features_from``: a folder of CLAM / TRIDENT
    ``NAME.h5`` to import instead (``patch_size`` px at pyramid level ``patch_level``, default from the
    files' attributes). ``no_pixels``: feature-only bundles (tiled storage). ``jobs``: processes;
    ``shard``: ``(I, N)``. Returns a summary: ``built`` / ``resumed`` / ``busy`` names, ``failed``
    (name → reason), ``dataset`` (the ``dataset.json`` dict, or None when slides remain), seconds,
    slides per minute and the peak resident memory of one job (bytes). ``reader``: what reads the slides
    (:data:`data_tools.slide_files.open.READERS`; recorded in the options when not ``"auto"``). ``folds``: K cross-validation
    folds recorded in ``dataset.json`` (:func:`make_plan`; patients from the ``labels`` table's patient column).
    ``mpp``: µm per level-0 px of every slide, for files that state none or a wrong one (``--mpp``; recorded in the
    options, each bundle and ``dataset.json``)."""
    from data_tools.datasets.discover import discover

    slides_dir, out = Path(slides_dir), Path(out)
    if no_pixels and not (encoder or features_from):
        raise HistojaxDataError(None, "--no-pixels needs features: give --encoder NAME or --features-from DIR")
    if encoder and features_from:
        raise HistojaxDataError(None, "give --encoder or --features-from, not both")
    if no_pixels:
        storage = "tiled"
    from data_tools.bundle import check_mpp

    check_mpp(slides_dir, mpp)  # before anything is read
    from data_tools.features import encoder_record

    if encoder is not None:  # a built-in name, or your own module:function, probed (a broken one refused)
        encoder_record(encoder)
    _check_out_apart(slides_dir, out)
    t0 = time.perf_counter()
    skipped: list = []  # files discovery passed over, with why (each also a warning): "skipped" in the summary
    entries = discover(
        slides_dir,
        annotations_dir=annotations,
        labels_csv=labels,
        skip=[out],
        allow_unmatched=allow_unmatched,
        skipped=skipped,
    )
    h5s = h5_index(features_from) if features_from else None
    if h5s:  # one encoder's features: files of different D refused before anything is built
        from data_tools.features.hdf5 import check_feature_dims

        check_feature_dims(h5s[e.name.lower()] for e in entries if e.name.lower() in h5s)
    mpps = check_scales(entries, magnification_range, reader, mpp)
    for line in dataset_scale(_encoder_of({"encoder": encoder, "features_from": features_from}), mpps)[1]:
        warnings.warn(f"{slides_dir}: {line}", stacklevel=2)  # one line each; recorded in dataset.json
    options = {
        "levels": sorted(set(int(v) for v in levels)),
        "tile_size": int(tile_size),
        "magnification_range": magnification_range,
        "storage": storage,
        "label_map": label_map or None,
        "encoder": encoder,
        "features_from": None if features_from is None else str(Path(features_from).resolve()),
        "patch_size": patch_size,
        "patch_level": patch_level,
        "no_pixels": bool(no_pixels),
        "test_fraction": test_fraction,
        "seed": int(seed),
        **({"reader": reader} if reader not in (None, "auto") else {}),  # absent: plans of before stay equal
        **({"mpp": float(mpp)} if mpp is not None else {}),
    }
    patients = read_patient_column(labels) if labels is not None else None  # the split and folds by patient
    plan = make_plan(entries, slides_dir, options, test_fraction, seed, folds=folds, patients=patients)
    for n, m in mpps.items():
        plan["slides"][n]["mpp"] = m
    if (out / "plan.json").exists() or (out / "plan.json").is_symlink():
        read_plan(out)  # another tool's plan.json: refused before anything is written
    check_dataset_json(out)
    out.mkdir(parents=True, exist_ok=True)
    with file_lock(out / ".dataset.lock", what=str(out)):
        _hold_run(out, plan)  # a run of other options holding this folder: refused, one line
        # --restart keeps dataset.json: the dataset stays loadable until the new one replaces it
        _agree(out, plan, restart=restart)
        _HELD[-1].share()
    removed = clean_stale(out / "bundles") + [
        f"annotations/{n}" for n in clean_stale(out / "annotations", lock_folder=out / "bundles")
    ]
    for sub in ("records", "records/failed"):
        removed += [f"{sub}/{n}" for n in clean_stale(out / sub, finished_features=False, lock_folder=out / "bundles")]
    if removed and progress:
        print(f"removed {len(removed)} leftovers of an interrupted run: {', '.join(removed[:5])}")
    mine = shard_names(plan["slides"], shard)
    jobs_list = [
        {
            "out": str(out),
            "name": n,
            "slide": plan["slides"][n],
            "options": options,
            "slides_dir": str(slides_dir),
            "progress": progress and jobs <= 1,
            "h5": None if h5s is None else h5s.get(n.lower()),
        }
        for n in mine
    ]
    results = []
    bar = tqdm(total=len(jobs_list), desc="dataset slides", unit="slide", disable=not progress)
    if jobs <= 1:
        for job in jobs_list:
            results.append(build_one(job))
            bar.update(1)
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed
        from concurrent.futures.process import BrokenProcessPool

        from data_tools.datasets.workers import die_with_parent, stop_workers_on_sigterm

        with (
            ProcessPoolExecutor(
                jobs,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=die_with_parent,
                initargs=(os.getpid(),),
            ) as pool,
            stop_workers_on_sigterm(pool),
        ):
            futures = {pool.submit(build_one, job): job["name"] for job in jobs_list}
            try:
                for fut in as_completed(futures):
                    results.append(fut.result())
                    bar.update(1)
            except BrokenProcessPool:
                done = {r["name"] for r in results}
                left = [n for n in futures.values() if n not in done]
                raise HistojaxDataError(
                    out,
                    f"a --jobs worker process died (killed, e.g. out of memory) while "
                    f"{len(left)} slide(s) were unfinished (e.g. {', '.join(left[:3])}); "
                    "finished slides are kept: rerun to resume, with fewer --jobs if memory "
                    "ran out",
                ) from None
    bar.close()
    dataset, missing, failed = merge_dataset(out)
    built = [r for r in results if r["status"] == "built"]
    seconds = time.perf_counter() - t0
    return {
        **run_summary(results),
        "failed_all": failed,
        "missing": missing,
        "dataset": dataset,
        "seconds": round(seconds, 2),
        "slides_per_minute": round(60 * len(built) / seconds, 2) if built else None,
        "peak_rss_bytes_per_job": max([r["record"]["peak_rss_bytes"] for r in built] or [0]),
        "shard": shard,
        "n_slides": len(plan["slides"]),
        "n_mine": len(mine),
        "skipped": [str(item) for item in skipped],
    }


__all__ = [
    "BUILD_ERRORS",
    "DATASET_DIGEST",
    "build_dataset",
    "build_one",
    "check_bundle_folder",
    "check_dataset_json",
    "check_scales",
    "check_scorable",
    "collect_records",
    "dataset_json_is_ours",
    "h5_index",
    "make_plan",
    "merge_dataset",
    "read_plan",
    "read_record",
    "record_path",
    "run_locked",
    "run_summary",
    "write_dataset_index",
    "write_dataset_json",
]
