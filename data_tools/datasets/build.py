"""Build a dataset from a folder of real slides (``histojax dataset SLIDES_DIR --out DIR``).

Layout of ``DIR``: ``bundles/NAME/`` (one bundle per slide), ``records/NAME.json`` (a finished
slide: its settings, label, split, figures) or ``records/NAME.failed.json`` (its one-line reason),
``plan.json`` (the options and the cohort every shard must agree on), ``annotations/NAME.geojson``
(NCRF JSON converted) and, once every slide has a record, ``dataset.json`` (the split that
``histojax.make(..., dataset=DIR)`` loads, the labels, the failures).

Restartable: a slide whose record matches its settings and whose bundle is there is not built
again; a killed run's temporaries are removed (:func:`data_tools.datasets.locks.clean_stale`).
Parallel: ``jobs`` processes on one machine; ``shard=(I, N)`` builds every N-th of the sorted slide
names starting at the I-th, so N machines sharing ``DIR`` build disjoint sets; each bundle is built
holding its own lock, so two processes never build one bundle. The run that finds every slide
recorded (or :func:`merge_dataset`) writes ``dataset.json``. A slide that fails is recorded with its
reason and the others still build.
"""
from __future__ import annotations

import json
import resource
import shutil
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from data_tools.bundle_format import read_metadata, write_json
from data_tools.datasets.locks import LockHeld, bundle_lock_path, clean_partial_features, clean_stale, file_lock
from data_tools.datasets.split import seeded_split, shard_names
from data_tools.errors import HistojaxDataError

KIND = "histojax dataset of real slides (data_tools dataset)"
MPP_TOLERANCE = 0.05  # relative: slides within 5 % µm/px share one --magnification-range


def _fingerprint(path: Path) -> dict:
    """Cheap identity of a slide file or DICOM folder: size in bytes and mtime (ns) of its files."""
    files = sorted(path.rglob("*")) if path.is_dir() else [path]
    stats = [f.stat() for f in files if f.is_file()]
    return {"bytes": int(sum(s.st_size for s in stats)),
            "mtime_ns": int(max((s.st_mtime_ns for s in stats), default=0))}


def _rel(path: Path, root: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(Path(root).resolve()))
    except ValueError:
        return str(Path(path).resolve())


def check_scales(entries, magnification_range) -> dict[str, float | None]:
    """µm/px of every slide; with one ``magnification_range`` for all, slides whose level-0 µm/px differ by
    more than 5 % (or some unknown) are an error naming two of them: one range would give them different
    physical scales."""
    from data_tools.slides import open_slide

    mpps: dict[str, float | None] = {}
    for e in entries:
        try:
            with open_slide(e.path) as reader:
                mpps[e.name] = reader.mpp
        except HistojaxDataError:
            mpps[e.name] = None  # unreadable: fails (with its reason) when built
        except Exception:  # noqa: BLE001 - any reader trouble shows up again, as a one-line failure, when built
            mpps[e.name] = None
    if magnification_range is not None:
        known = {n: m for n, m in mpps.items() if m}
        unknown = [e for e in entries if not mpps.get(e.name)]
        if known and unknown:
            raise HistojaxDataError(unknown[0].path, f"has no µm/px while {next(iter(known))} has "
                                    f"{next(iter(known.values())):.4g}: one --magnification-range "
                                    f"{magnification_range:g} would mix scales; build them in separate datasets")
        if known:
            lo, hi = min(known, key=known.get), max(known, key=known.get)
            if known[hi] > known[lo] * (1 + MPP_TOLERANCE):
                raise HistojaxDataError(next(e.path for e in entries if e.name == hi),
                                        f"is {known[hi]:.4g} µm/px but {lo} is {known[lo]:.4g} µm/px: one "
                                        f"--magnification-range {magnification_range:g} would give their levels "
                                        "different physical scales; omit it (each slide its own range) or build "
                                        "them in separate datasets")
    return mpps


def make_plan(entries, slides_dir, options: dict, test_fraction: float, seed: int) -> dict:
    """The cohort and options every shard must agree on: slide → (path relative to ``slides_dir``,
    annotation, label, split)."""
    fixed = {e.name: e.split for e in entries if e.split}
    if fixed and len(fixed) != len(entries):
        loose = [e.name for e in entries if not e.split]
        raise HistojaxDataError(loose[0], f"{len(loose)} slide(s) have no split while others do (e.g. {loose[:3]})")
    if fixed:
        split = fixed
        rule = "given (CAMELYON16 official split or the label table's split column)"
    else:
        train, test = seeded_split([e.name for e in entries], {e.name: e.label for e in entries}, test_fraction, seed)
        split = {**{n: "train" for n in train}, **{n: "test" for n in test}}
        rule = f"seeded (seed {seed}), stratified by label, {test_fraction:.0%} of each label in test"
    slides = {e.name: {"path": _rel(e.path, slides_dir),
                       "annotation": None if e.annotation is None else _rel(e.annotation, slides_dir),
                       "annotation_kind": e.annotation_kind, "label": int(e.label), "label_source": e.label_source,
                       "split": split[e.name]} for e in entries}
    return {"kind": KIND, "options": options, "split_rule": rule, "slides": slides}


def _agree(out: Path, plan: dict) -> None:
    """Write ``plan.json`` if absent; else refuse a run whose options or cohort differ (one line)."""
    path = out / "plan.json"
    if path.is_file():
        try:
            old = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            old = None
        if old is not None and old != plan:
            what = [k for k in ("options", "slides", "split_rule") if old.get(k) != plan.get(k)]
            detail = ""
            if old.get("options") != plan.get("options"):
                diff = sorted(k for k in set(old["options"]) | set(plan["options"])
                              if old["options"].get(k) != plan["options"].get(k))
                detail = f" (options {diff})"
            elif old.get("slides") != plan.get("slides"):
                diff = sorted(k for k in set(old["slides"]) | set(plan["slides"])
                              if old["slides"].get(k) != plan["slides"].get(k))
                detail = f" (slides {diff[:4]})"
            raise HistojaxDataError(path, f"this dataset was started with a different {' and '.join(what)}{detail}; "
                                          "use the same command, a new --out, or --restart")
    write_json(path, plan)


def _settings_key(name: str, slide: dict, options: dict, slides_dir: Path) -> dict:
    return {"slide": slide, "options": options,
            "fingerprint": _fingerprint(slides_dir / slide["path"]),
            "annotation_fingerprint": None if slide["annotation"] is None
            else _fingerprint(slides_dir / slide["annotation"])}


def record_path(out: Path, name: str, failed: bool = False) -> Path:
    """``OUT/records/NAME.json`` (a finished slide) or ``OUT/records/NAME.failed.json`` (its failure)."""
    (Path(out) / "records").mkdir(parents=True, exist_ok=True)
    return Path(out) / "records" / f"{name}{'.failed' if failed else ''}.json"


def read_record(out: Path, name: str, failed: bool = False) -> dict | None:
    """The record (or failure record) of slide ``name`` in the dataset ``out``; None when absent or unreadable."""
    try:
        rec = json.loads(record_path(out, name, failed).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    return rec if isinstance(rec, dict) else None


BUILD_ERRORS = (HistojaxDataError, OSError, ValueError, MemoryError)
"""What a slide's build may raise that is the slide's fault: recorded, and the cohort goes on."""


def run_locked(out, name: str, work, current=None) -> dict:
    """Build slide ``name`` of the dataset ``out`` holding its bundle's lock (``bundles/.NAME.dataset-lock``,
    not blocking: a slide another process or shard is building is reported ``busy`` and skipped).
    ``current(record) -> bool``: a record that needs no rebuild (``resumed``; default: always rebuild).
    ``work() -> record`` builds it; the record is written to ``records/NAME.json``. A build error
    (:data:`BUILD_ERRORS`) removes the slide's bundle and writes ``records/NAME.failed.json`` with the
    one-line reason. Returns ``{"name", "status": "built" | "resumed" | "failed" | "busy", "reason"?,
    "record"?}``. The one per-slide step of ``data_tools dataset`` and ``data_tools c16``."""
    out = Path(out)
    bundle = out / "bundles" / name
    t0 = time.perf_counter()
    try:
        lock = file_lock(bundle_lock_path(bundle), blocking=False, what=f"bundle {name}")
        lock.__enter__()
    except LockHeld:
        return {"name": name, "status": "busy"}
    try:
        rec = read_record(out, name)
        if rec is not None and current is not None and current(rec) and (bundle / "metadata.json").is_file():
            clean_partial_features(bundle)
            return {"name": name, "status": "resumed", "record": rec}
        record_path(out, name).unlink(missing_ok=True)
        try:
            rec = work()
        except BUILD_ERRORS as e:
            reason = _one_line(e)
            if bundle.exists():
                shutil.rmtree(bundle, ignore_errors=True)
            write_json(record_path(out, name, failed=True), {"name": name, "reason": reason})
            return {"name": name, "status": "failed", "reason": reason}
        rec.setdefault("seconds", round(time.perf_counter() - t0, 2))
        rec.setdefault("peak_rss_bytes", resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)
        write_json(record_path(out, name), rec)
        record_path(out, name, failed=True).unlink(missing_ok=True)
        return {"name": name, "status": "built", "record": rec}
    finally:
        lock.__exit__(None, None, None)


def run_summary(results: list[dict]) -> dict:
    """This run's slides by the status :func:`run_locked` gave them: ``built`` / ``resumed`` / ``busy`` names
    and ``failed`` (name → reason)."""
    return {**{k: [r["name"] for r in results if r["status"] == k] for k in ("built", "resumed", "busy")},
            "failed": {r["name"]: r["reason"] for r in results if r["status"] == "failed"}}


def collect_records(out, names, current=None) -> tuple[dict[str, dict], dict[str, str], list[str]]:
    """The finished slides among ``names`` of the dataset ``out``: ``(records, failed, missing)`` —
    name → record (without its ``settings``) for each slide with a record (``current(record)`` true,
    when given) and a bundle; name → reason for each recorded failure; the names with neither (still to
    build, by this run or another shard). The one reader of records for ``merge`` and ``c16``."""
    out = Path(out)
    records, failed, missing = {}, {}, []
    for name in names:
        rec = read_record(out, name)
        if rec is not None and (current is None or current(rec)) \
                and (out / "bundles" / name / "metadata.json").is_file():
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
    bundle = out / "bundles" / name
    key = _settings_key(name, slide, opts, slides_dir)
    return run_locked(out, name, lambda: _build(out, name, slide, opts, slides_dir, bundle, key, job.get("h5"),
                                                job.get("progress", False)),
                      current=lambda rec: rec.get("settings") == key)


def _one_line(e: BaseException) -> str:
    from data_tools.cli_output import one_line, os_error_text

    return one_line(os_error_text(e) if isinstance(e, OSError) else str(e) or type(e).__name__)


def _build(out, name, slide, opts, slides_dir, bundle, key, h5, progress) -> dict:
    """The work of :func:`build_one` (lock held)."""
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
        build_bundle(path, bundle, annotations_path=ann, level_sets=opts["levels"], tile_size=opts["tile_size"],
                     magnification_range=opts["magnification_range"], storage=opts["storage"], overwrite=True,
                     progress=progress, label_map=opts["label_map"])
    notes = sorted({_one_line(w.message) for w in caught})
    meta = read_metadata(bundle)
    tissue = np.load(bundle / meta.tissue_file, allow_pickle=False)
    if not tissue.any():
        raise HistojaxDataError(path, "no tissue found (the coarsest level is blank glass): not a usable slide")
    tumour_px = float((meta.annotations or {}).get("tumour_area_px") or 0.0)
    if slide["label"] == 1 and slide["label_source"].startswith("annotated") and tumour_px <= 0:
        raise HistojaxDataError(ann, "annotation has no tumour polygon (groups map to "
                                f"{(meta.annotations or {}).get('n_polygons')}); label the slide in --labels or "
                                "fix --label-map")
    if slide["label"] == 0 and tumour_px > 0:
        raise HistojaxDataError(ann, f"marks {tumour_px:.0f} px² of tumour but the slide is labelled normal "
                                     f"({slide['label_source']})")
    if h5 is not None:
        from data_tools.features.hdf5 import import_features

        import_features(bundle, h5, patch_size=opts["patch_size"], level=opts["patch_level"])
    elif opts["encoder"]:
        from data_tools.features.grid import compute_features

        compute_features(bundle, encoder_name=opts["encoder"], progress=progress, verify=False)
    clean_partial_features(bundle)
    if opts["no_pixels"]:
        from data_tools.bundle_format import drop_pixels

        drop_pixels(bundle)
    meta = read_metadata(bundle)
    return {"name": name, "bundle": f"bundles/{name}", "source": slide["path"], "label": slide["label"],
            "label_source": slide["label_source"], "split": slide["split"], "settings": key,
            "format": meta.source.get("format"), "width": meta.source.get("width"),
            "height": meta.source.get("height"), "mpp": meta.source.get("mpp"), "storage": meta.storage,
            "tumour_area_level0_px2": tumour_px, "encoder": (meta.features or {}).get("encoder"),
            "pixels_kept": len(meta.pixel_levels) == len(meta.levels),
            "bundle_bytes": sum(f.stat().st_size for f in bundle.rglob("*") if f.is_file()),
            "device_bytes_pixels": meta.device_bytes, "notes": notes}


def write_dataset_json(out, plan: dict, records: dict[str, dict], failed: dict[str, str], extra=None) -> dict:
    """Write ``OUT/dataset.json`` (atomically, holding ``OUT/.dataset.lock``): ``train`` / ``test`` lists of
    the built bundles (``bundles/NAME``) by the plan's split, ``labels`` (name → 0/1), ``slides`` (the
    records), ``failed`` (name → reason). Returns it."""
    out = Path(out)
    names = sorted(records)
    dataset = {
        "kind": plan.get("kind", KIND), "split_rule": plan.get("split_rule"), "options": plan.get("options"),
        "encoder": _encoder_of(plan.get("options") or {}),
        "train": [f"bundles/{n}" for n in names if plan["slides"][n]["split"] == "train"],
        "test": [f"bundles/{n}" for n in names if plan["slides"][n]["split"] == "test"],
        "labels": {n: int(plan["slides"][n]["label"]) for n in names},
        "failed": dict(sorted(failed.items())),
        "slides": [records[n] for n in names],
        **(extra or {}),
    }
    return write_dataset_index(out, dataset)


def _encoder_of(options: dict) -> str | None:
    """The feature grids' encoder, as the ids' ``dataset_encoder`` checks it: ``--encoder``'s name, ``"imported"``
    for ``--features-from``, None without features."""
    from data_tools.features import encoder_name  # your own encoder (module:function): the name it records

    return encoder_name(options.get("encoder")) or ("imported" if options.get("features_from") else None)


def write_dataset_index(out, dataset: dict) -> dict:
    """Write ``dataset`` as ``OUT/dataset.json`` atomically, holding ``OUT/.dataset.lock`` (the one writer of
    ``dataset.json`` for ``data_tools dataset`` and ``c16``); returns it."""
    out = Path(out)
    with file_lock(out / ".dataset.lock", what=str(out)):
        write_json(out / "dataset.json", dataset)
    return dataset


def merge_dataset(out) -> tuple[dict | None, list[str], dict[str, str]]:
    """Read ``OUT/plan.json`` and every record; write ``dataset.json`` when every slide has one. Returns
    ``(dataset or None, names still missing, failed name → reason)``."""
    out = Path(out)
    try:
        plan = json.loads((out / "plan.json").read_text())
    except FileNotFoundError:
        raise HistojaxDataError(out, "no plan.json: not a dataset started by `histojax dataset`") from None
    except json.JSONDecodeError as e:
        raise HistojaxDataError(out / "plan.json", f"malformed JSON ({e})") from None
    records, failed, missing = collect_records(out, sorted(plan["slides"]))
    if missing:
        return None, missing, failed
    return write_dataset_json(out, plan, records, failed), [], failed


def build_dataset(slides_dir, out, *, labels=None, annotations=None, levels=(3, 5, 7), tile_size: int = 128,
                  magnification_range: float | None = None, storage: str = "auto", label_map=None,
                  encoder: str | None = None, features_from=None, patch_size: int | None = None,
                  patch_level: int | None = None, no_pixels: bool = False, test_fraction: float = 0.25,
                  seed: int = 0, jobs: int = 1, shard: tuple[int, int] | None = None, restart: bool = False,
                  allow_unmatched: bool = False, progress: bool = True) -> dict:
    """Build (or finish) the dataset ``out`` from the slides under ``slides_dir`` (see the module doc and
    :mod:`data_tools.datasets.discover`). ``levels`` / ``tile_size`` (px) / ``magnification_range`` (the
    coarsest downsample; default each slide's own) / ``storage`` / ``label_map``: as ``build``.
    ``encoder``: compute each bundle's feature grid; ``features_from``: a folder of CLAM / TRIDENT
    ``NAME.h5`` to import instead (``patch_size`` px at pyramid level ``patch_level``, default from the
    files' attributes). ``no_pixels``: feature-only bundles (tiled storage). ``jobs``: processes;
    ``shard``: ``(I, N)``. Returns a summary: ``built`` / ``resumed`` / ``busy`` names, ``failed``
    (name → reason), ``dataset`` (the ``dataset.json`` dict, or None when slides remain), seconds,
    slides per minute and the peak resident memory of one job (bytes)."""
    from data_tools.datasets.discover import discover

    slides_dir, out = Path(slides_dir), Path(out)
    if no_pixels and not (encoder or features_from):
        raise HistojaxDataError(None, "--no-pixels needs features: give --encoder NAME or --features-from DIR")
    if encoder and features_from:
        raise HistojaxDataError(None, "give --encoder or --features-from, not both")
    if no_pixels:
        storage = "tiled"
    from data_tools.features import encoder_record

    if encoder is not None:  # a built-in name, or your own module:function, probed (a broken one refused)
        encoder_record(encoder)
    t0 = time.perf_counter()
    entries = discover(slides_dir, annotations_dir=annotations, labels_csv=labels, skip=[out],
                       allow_unmatched=allow_unmatched)
    h5s = h5_index(features_from) if features_from else None
    mpps = check_scales(entries, magnification_range)
    options = {"levels": sorted(set(int(v) for v in levels)), "tile_size": int(tile_size),
               "magnification_range": magnification_range, "storage": storage, "label_map": label_map or None,
               "encoder": encoder,
               "features_from": None if features_from is None else str(Path(features_from).resolve()),
               "patch_size": patch_size, "patch_level": patch_level, "no_pixels": bool(no_pixels),
               "test_fraction": test_fraction, "seed": int(seed)}
    plan = make_plan(entries, slides_dir, options, test_fraction, seed)
    for n, m in mpps.items():
        plan["slides"][n]["mpp"] = m
    out.mkdir(parents=True, exist_ok=True)
    with file_lock(out / ".dataset.lock", what=str(out)):
        if restart:
            for p in (out / "plan.json", out / "dataset.json"):
                p.unlink(missing_ok=True)
        _agree(out, plan)
    removed = clean_stale(out / "bundles") + [f"annotations/{n}" for n in clean_stale(out / "annotations",
                                                                                      lock_folder=out / "bundles")]
    if removed and progress:
        print(f"removed {len(removed)} leftovers of an interrupted run: {', '.join(removed[:5])}")
    mine = shard_names(plan["slides"], shard)
    jobs_list = [{"out": str(out), "name": n, "slide": plan["slides"][n], "options": options,
                  "slides_dir": str(slides_dir), "progress": progress and jobs <= 1,
                  "h5": None if h5s is None else h5s.get(n.lower())} for n in mine]
    results = []
    bar = tqdm(total=len(jobs_list), desc="dataset slides", unit="slide", disable=not progress)
    if jobs <= 1:
        for job in jobs_list:
            results.append(build_one(job))
            bar.update(1)
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
            for fut in as_completed([pool.submit(build_one, job) for job in jobs_list]):
                results.append(fut.result())
                bar.update(1)
    bar.close()
    dataset, missing, failed = merge_dataset(out)
    built = [r for r in results if r["status"] == "built"]
    seconds = time.perf_counter() - t0
    return {**run_summary(results),
            "failed_all": failed, "missing": missing, "dataset": dataset, "seconds": round(seconds, 2),
            "slides_per_minute": round(60 * len(built) / seconds, 2) if built else None,
            "peak_rss_bytes_per_job": max([r["record"]["peak_rss_bytes"] for r in built] or [0]),
            "shard": shard, "n_slides": len(plan["slides"]), "n_mine": len(mine)}


__all__ = ["BUILD_ERRORS", "build_dataset", "build_one", "check_scales", "collect_records", "h5_index", "make_plan",
           "merge_dataset", "read_record", "record_path", "run_locked", "run_summary", "write_dataset_index", "write_dataset_json"]
