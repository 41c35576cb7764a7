"""The true-scale CAMELYON16 benchmark dataset (``python -m data_tools c16``).

GEOMETRY IS REAL CAMELYON16 (NCRF polygons, every tumour at its true size relative to the tissue and
the view), PIXELS ARE REAL PatchCamelyon PATCHES ARRANGED BY US (a mosaic, see
:mod:`data_tools.datasets.c16.mosaic`), NOT SCANNED SLIDES. Geometry: :mod:`data_tools.datasets.c16.layout`.

Layout of ``OUT``: ``slides/NAME.tif`` (pyramidal JPEG-tiled TIFF) with ``NAME.geojson`` (tumour and
tissue, output px) and ``NAME.provenance.json`` beside it, ``bundles/NAME/`` (tiled bundles) and
``dataset.json`` (split, provenance, scale, per-slide figures) written last.

Restartable per slide: a slide whose TIFF, GeoJSON and provenance exist with the same settings is
not made again, nor its bundle when the bundle's source checksum matches; the TIFF is written to
``slides/.NAME.tif.tmp-PID`` and renamed. A bundle is built (or, when up to date, hard-linked, then given its
feature grid or stripped of pixels) into a hidden ``bundles/.NAME.tmp-*`` and swapped onto ``bundles/NAME``
only once whole (as ``data_tools dataset`` does: :func:`data_tools.datasets.build.run_locked`), so a failed
rebuild (a full disk, a killed feature step) leaves the previous bundle and its record as they were. Locks, records, shards and ``dataset.json`` go through the code of
``data_tools dataset`` (:mod:`data_tools.datasets.build`, :mod:`data_tools.datasets.locks`): each slide is
made holding ``bundles/.NAME.dataset-lock`` (``flock``, released by the kernel even on SIGKILL) and
recorded in ``records/NAME.json``; a run first deletes the hidden temporaries of slides nobody is making.
"""

from __future__ import annotations

import json
import resource
import sys
import time
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from data_tools.bundle_files.format import sha256
from data_tools.bundle_files.reading import bundle_damage, read_metadata
from data_tools.bundle_files.writes import atomic_file, write_json
from data_tools.datasets.c16.inputs import check_known_inputs, differing_lines
from data_tools.datasets.c16.layout import C16_MPP, donor_for, layout
from data_tools.datasets.c16.mosaic import PIXELS_NOTE, Texture, write_slide_tiff
from data_tools.datasets.pcam_bank import CITATION, load_bank
from data_tools.datasets.split import grouped_split as split_slides  # one home for splits (data_tools.datasets)
from data_tools.errors import HistojaxDataError

FULL_DOWNSAMPLE = 8.0  # the full benchmark: CAMELYON16 level 0 / 8 = 1.94 µm/px (see docs/c16-benchmark.md)
SMALL_DOWNSAMPLE = 32.0  # the small variant (tests, demo): 7.8 µm/px
COARSEST = 256.0  # the coarsest env level is CAMELYON16 level 0 / 256 for every downsample
SMALL_SLIDES = ("Tumor_072", "Tumor_082", "Tumor_094", "Normal_017", "Normal_042", "Normal_108")
TILE_SIZE = 128
LEVEL_SETS = (3, 5, 7)
DATASET_FORMAT = 2  # 2: train/test slides textured from disjoint PCam patch pools (recorded in dataset.json)
LICENCE = (
    "tumour and tissue polygons: CAMELYON16 ground truth (CC0 1.0) as converted to JSON by "
    "baidu-research/NCRF (Apache-2.0); tissue outlines of tumor_001/013/021/031/051/092: pathml-tutorial; "
    "pixels: PatchCamelyon patches, CC0 1.0 — " + CITATION
)


def clean_stale(out_dir: Path) -> list[str]:
    """Delete the hidden temporaries of killed runs (``slides/.*.tmp-*``, ``bundles/.*.tmp-*``,
    ``bundles/.*.old-*``, of any name) and the ``features.partial/`` of finished bundles; returns their
    names. Through the shared dataset code (:func:`data_tools.datasets.locks.clean_stale`): a temporary
    whose name a live process is building is left alone."""
    from data_tools.datasets.locks import clean_stale as _clean

    return [f"bundles/{n}" for n in _clean(out_dir / "bundles")] + [
        f"slides/{n}" for n in _clean(out_dir / "slides", finished_features=False, lock_folder=out_dir / "bundles")
    ]


def _slide_settings(name, downsample, seed, bank, jpeg_quality, sha, donor=None, pool=None) -> dict:
    from data_tools.datasets.c16 import mosaic as c16_mosaic

    return {
        "name": name,
        "downsample": float(downsample),
        "seed": int(seed),
        "bank": bank.source,
        "bank_patches": len(bank),
        "jpeg_quality": int(jpeg_quality),
        "polygons_sha256": sha,
        "colour_match": c16_mosaic.COLOUR_MATCH,
        "tissue_donor": donor.name if donor is not None else None,
        "donor_polygons_sha256": donor.sha256 if donor is not None else None,
        "patch_pool": pool,
    }


def make_slide(
    out_dir: Path,
    slide,
    donor,
    downsample: float,
    seed: int,
    bank,
    jpeg_quality: int = 85,
    progress: bool = True,
    pool: str | None = None,
) -> dict:
    """Write ``slides/NAME.tif`` (+ ``.geojson``, ``.provenance.json``) unless a finished one with the same
    settings (the donor of its tissue and its patch pool included) is there; returns its provenance.
    ``bank``: the patches this slide may draw (its split's pool); ``pool``: that pool's name."""
    from data_tools.datasets.synth.dataset import _geojson

    folder = out_dir / "slides"
    folder.mkdir(parents=True, exist_ok=True)
    tiff = folder / f"{slide.name}.tif"
    prov_file = tiff.with_suffix(".provenance.json")
    settings = _slide_settings(slide.name, downsample, seed, bank, jpeg_quality, slide.sha256, donor, pool)
    if prov_file.is_file() and tiff.is_file() and tiff.with_suffix(".geojson").is_file():
        try:
            prov = json.loads(prov_file.read_text())
            if prov.get("settings") == settings:
                return prov
        except (OSError, json.JSONDecodeError):
            pass
    t0 = time.perf_counter()
    lay = layout(slide, downsample, donor)
    texture = Texture(bank, downsample, seed)
    description = (
        f"histojax true-scale CAMELYON16 slide {slide.name}. {PIXELS_NOTE} Scale: CAMELYON16 level 0 / "
        f"{downsample:g} = {lay.mpp:.4g} um/px. Tissue: {lay.provenance['tissue']}. Seed {seed}."
    )
    bar = tqdm(
        total=-(-lay.size[0] // 256) * -(-lay.size[1] // 256),
        unit="tile",
        leave=False,
        desc=f"{slide.name} ({lay.size[0]}×{lay.size[1]} px)",
        disable=not progress,
        mininterval=1.0,
    )
    try:
        with atomic_file(tiff) as tmp:
            info = write_slide_tiff(lay, texture, tmp, description, jpeg_quality, progress=bar.update)
    finally:
        bar.close()
    summary = f"geometry real CAMELYON16 {slide.name}, pixels real PCam patches arranged by histojax"
    tiff.with_suffix(".geojson").write_text(json.dumps(_geojson(lay.tumour, lay.tissue, summary), allow_nan=False))
    area = float(lay.size[0]) * lay.size[1]
    prov = {
        "settings": settings,
        "note": PIXELS_NOTE,
        "licence": LICENCE,
        "summary": summary,
        **lay.provenance,
        "stain_od_factors": texture.stain,
        "patch_pool": pool,
        "patch_names": {str(lab): names for lab, names in texture.patch_names.items()},
        "patch_side_px": texture.side,
        "patch_step_px": texture.step,
        "tumour_fraction_of_canvas": float(lay.tumour.area) / area,
        "tumour_fraction_of_tissue": float(lay.tumour.area) / max(float(lay.tissue.area), 1.0),
        "tissue_fraction_of_canvas": float(lay.tissue.area) / area,
        **info,
        "tiff_bytes": tiff.stat().st_size,
        "tiff_sha256": sha256(tiff),
        "seconds": round(time.perf_counter() - t0, 2),
    }
    write_json(prov_file, prov)
    return prov


def has_grid_of(meta, encoder: str) -> bool:
    """True when the bundle of ``meta`` holds the feature grid of ``--encoder encoder`` (a built-in name, or
    your own ``module:function``: its recorded name and version)."""
    from data_tools.features import encoder_record

    want, have = encoder_record(encoder), meta.features or {}
    return have.get("encoder") == want["encoder"] and have.get("encoder_version") == want.get("encoder_version")


def make_bundle(
    out_dir: Path,
    name: str,
    prov: dict,
    magnification_range: float,
    progress: bool = False,
    encoder: str | None = None,
    into: Path | None = None,
) -> dict:
    """Build (unless up to date) the tiled bundle ``bundles/NAME`` of a made slide; returns its metadata.
    Up to date: made from the same TIFF and range, and holding its pixels, or (a feature-only bundle) the
    feature grid of ``encoder`` (the pixels are needed again to embed them with another encoder).
    ``into``: a folder that does not exist yet (the hidden temporary of a staged build): the bundle is built
    there, or an up-to-date ``bundles/NAME`` is hard-linked there (:func:`_link_bundle`), and ``bundles/NAME``
    is left untouched."""
    from data_tools.bundle import build_bundle

    bundle = out_dir / "bundles" / name
    target = bundle if into is None else Path(into)
    if (bundle / "metadata.json").is_file():
        try:
            meta = read_metadata(bundle)
            whole = len(meta.pixel_levels) == len(meta.levels)
            if (
                meta.source["sha256"] == prov["tiff_sha256"]
                and meta.magnification_range == magnification_range
                and (whole or (encoder is not None and has_grid_of(meta, encoder)))
                and (target == bundle or bundle_damage(bundle) is None)
            ):  # a damaged bundle is built again
                if target == bundle:
                    return meta
                _link_bundle(bundle, target)
                return read_metadata(target)
        except (HistojaxDataError, KeyError):
            pass
    tiff = out_dir / "slides" / f"{name}.tif"
    build_bundle(
        tiff,
        target,
        annotations_path=tiff.with_suffix(".geojson"),
        level_sets=LEVEL_SETS,
        tile_size=TILE_SIZE,
        magnification_range=magnification_range,
        storage="tiled",
        overwrite=True,
        progress=progress,
    )
    return read_metadata(target)


def _link_bundle(bundle: Path, into: Path) -> None:
    """Fill the new folder ``into`` with the files of the bundle ``bundle`` (and of its ``features.partial/``,
    so a feature step that was killed resumes): arrays hard-linked (no copy on disk; histojax never writes
    into a bundle's file, it writes a new file and renames it, so the two folders never change each other's
    files), other files copied; a filesystem without hard links gets copies. Only the bundle's own regular
    files are taken (:func:`data_tools.bundle_files.safe_files.own_file`); links, folders and hidden temporaries of
    killed writes are left out."""
    import os
    import shutil

    from data_tools.bundle_files.safe_files import own_file
    from data_tools.errors import BundleError

    def put(src_dir: Path, dst_dir: Path) -> None:
        dst_dir.mkdir(exist_ok=True)  # the staged temporary exists already (holding histojax's marker)
        for entry in sorted(src_dir.iterdir()):
            if entry.name.startswith("."):
                continue  # the hidden temporary of a write that was killed: not carried over
            try:
                src = own_file(src_dir, entry.name)
            except BundleError:
                continue  # a folder, a link or odd entry: not a file of the bundle
            dst = dst_dir / entry.name
            if entry.suffix == ".npy":
                try:
                    os.link(src, dst)
                    continue
                except OSError:
                    pass
            shutil.copyfile(src, dst)

    put(bundle, into)
    partial = bundle / "features.partial"
    if partial.is_dir() and not partial.is_symlink():
        put(partial, into / "features.partial")


def _feature_layout_bytes(meta) -> int | None:
    """Device bytes of the slide in the feature-only layout with every bundle level (tumour tables and the
    feature grid; None without a feature grid)."""
    from data_tools.bundle_files.format import slide_device_bytes

    if not meta.features:
        return None
    return slide_device_bytes(meta, list(range(len(meta.levels))), pixels=False, features=True)


def _views_ge(meta: dict, bundle: Path, threshold: float = 0.5) -> int:
    """Grid-aligned finest-level views with tumour fraction ≥ ``threshold`` (from the SAT pool)."""
    from data_tools.bundle import load_bundle

    lv = load_bundle(bundle, verify=False, levels=[0]).tumour[0]
    t = TILE_SIZE
    counts = np.asarray(lv.pool[:, t, t]).astype(np.int64)[lv.index]
    return int((counts >= threshold * t * t).sum())


def slide_seed(seed: int, name: str) -> int:
    """The texture seed of slide ``name`` (the same in any subset or order)."""
    import zlib

    return (int(seed) * 1_000_003 + zlib.crc32(name.encode())) & 0x7FFFFFFF


_WORKER: dict = {}


def _init_worker(banks: dict, progress: bool) -> None:
    """``banks``: the patch bank of each split (``{"train": ..., "test": ...}``)."""
    _WORKER.update(banks=banks, progress=progress)


def scale_remedy(encoder: str, downsample: float) -> str:
    """What the scale warning of a c16 slide offers (c16 has no ``--mpp``: its µm/px is CAMELYON16's times
    ``--downsample``, known, not a file's to correct): the ``--downsample`` at the encoder's training scale."""
    from data_tools.features.encoders import ENCODER_MPP

    want = ENCODER_MPP.get(str(encoder))
    at = f"the c16 slides are at CAMELYON16's {C16_MPP} µm/px × --downsample {downsample:g}"
    if want is None:
        return at
    return f"{at}: build them with --downsample {want / C16_MPP:.3g} for {encoder}'s {want} µm/px"


def _one_slide(job, bundle: Path) -> dict:
    """Make one slide and its bundle (skipping what is done) into ``bundle`` (a hidden temporary folder, not
    there yet, swapped onto ``bundles/NAME`` by the caller once whole); its record for ``dataset.json``."""
    out_dir, slide, donor, d, seed, jpeg_quality, mag, encoder, no_pixels, side = job
    s0 = time.perf_counter()
    name = slide.name
    prov = make_slide(
        out_dir, slide, donor, d, seed, _WORKER["banks"][side], jpeg_quality, _WORKER["progress"], pool=side
    )
    meta = make_bundle(out_dir, name, prov, mag, encoder=encoder if no_pixels else None, into=bundle)
    if encoder and not has_grid_of(meta, encoder):
        from data_tools.features.grid import compute_features

        compute_features(
            bundle,
            encoder_name=encoder,
            progress=_WORKER["progress"],
            verify=False,
            scale_remedy=scale_remedy(encoder, d),
        )
        meta = read_metadata(bundle)
    from data_tools.datasets.locks import clean_partial_features

    clean_partial_features(bundle)  # a kill during the feature step, then a rerun: no empty features.partial/
    if no_pixels and len(meta.pixel_levels) > 1:
        from data_tools.bundle import drop_pixels

        drop_pixels(bundle)
        meta = read_metadata(bundle)
    return {
        "name": name,
        "bundle": f"bundles/{name}",
        "tiff": f"slides/{name}.tif",
        "label": int(slide.is_tumour_slide),
        "split": side,
        "patch_pool": side,
        "tissue": prov["tissue"],
        "tissue_donor": prov.get("tissue_donor"),
        "canvas": prov["canvas"],
        "mpp": prov["mpp"],
        "tumour_area_level0_px2": prov["tumour_area_level0_px2"],
        "tumour_fraction_of_tissue": round(prov["tumour_fraction_of_tissue"], 6),
        "finest_views_ge50": _views_ge(meta, bundle),
        "stain_od_factors": prov["stain_od_factors"],
        "tiff_bytes": prov["tiff_bytes"],
        "bundle_bytes": sum(f.stat().st_size for f in bundle.iterdir()),
        "device_bytes_pixels": meta.device_bytes,
        "device_bytes_features": _feature_layout_bytes(meta),
        "pixels_kept": len(meta.pixel_levels) == len(meta.levels),
        "encoder": (meta.features or {}).get("encoder"),
        "seconds_slide": prov["seconds"],
        "seconds_total": round(time.perf_counter() - s0, 2),
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
    }


def _locked_slide(job) -> dict:
    """One slide through the shared per-slide step (:func:`data_tools.datasets.build.run_locked`: the bundle's
    lock, ``records/NAME.json``, a failure recorded with its reason); its record carries the set's settings,
    and a slide recorded with the same settings (its bundle there) is not looked at again. Staged: the bundle
    is made in a hidden ``bundles/.NAME.tmp-*`` and swapped in once whole; a failure removes only that, so a
    previous bundle and its record stay."""
    from data_tools.datasets.build import run_locked

    out_dir, name, set_key = job[0], job[1].name, job[-1]
    return run_locked(
        out_dir,
        name,
        lambda folder: {**_one_slide(job[:-1], folder), "settings": set_key},
        current=lambda rec: rec.get("settings") == set_key,
        staged=True,
    )


def _adopt_old_records(out_dir: Path, set_key: dict, universe: list[str]) -> None:
    """Give the slides of a ``dataset.json`` written before records existed (same set, bundle still there)
    a record, so that a rerun keeps them."""
    from data_tools.datasets.build import read_record, record_path

    old_file = out_dir / "dataset.json"
    if not old_file.is_file():
        return
    try:
        old = json.loads(old_file.read_text())
    except (OSError, json.JSONDecodeError):
        return
    if not isinstance(old, dict) or any(old.get(k) != set_key[k] for k in _SAME_SET_KEYS):
        return
    for r in old.get("slides", []):
        name = r.get("name") if isinstance(r, dict) else None
        if name in universe and read_record(out_dir, name) is None and (out_dir / "bundles" / name).is_dir():
            write_json(record_path(out_dir, name), {**r, "settings": set_key})


def make_c16_dataset(
    out_dir,
    annotations=None,
    patches=None,
    small: bool = False,
    downsample: float | None = None,
    names=None,
    n_tumour: int | None = None,
    n_normal: int | None = None,
    seed: int = 0,
    test_fraction: float = 0.25,
    features: bool | str = False,
    jpeg_quality: int = 85,
    progress: bool = True,
    workers: int = 1,
    no_pixels: bool = False,
    test_patches=None,
    shard: tuple[int, int] | None = None,
    merge: bool = False,
    folds: int | None = None,
) -> dict:
    """Make (or finish) the true-scale CAMELYON16 dataset in ``out_dir`` (see the module doc).

    ``annotations``: a folder or ``.tar.gz`` of NCRF JSON files (default: the 6 shipped with the
    package, enough for ``small``). ``patches``: PCam patches (folder, ``.tar.gz`` or bank ``.npz``;
    default the shipped 1,000-patch bank), cut by the pool rule (:func:`data_tools.datasets.pcam_bank.split_pools`)
    into a training pool (textures the train split's slides; the only patches ``pcam-cnn`` was trained on)
    and a test pool (the test split's); ``test_patches``: texture the test split from this other patch set
    entirely instead (e.g. PCam's own valid/test patches). ``small``: the 6 slides of ``SMALL_SLIDES`` at
    downsample 32 (seconds). ``downsample``: output px per CAMELYON16 level-0 px (default 8, small 32).
    ``names`` / ``n_tumour`` / ``n_normal``: a subset (default every slide found). A subset is a part of the
    whole set, never a set of its own: the split, the tissue donors and hence every slide's pixels are those
    of the whole set (all slides of ``annotations``), the donors' polygons are read even when the donor is
    not built, and a ``dataset.json`` already in ``out_dir`` keeps its other slides. The env's coarsest level
    is CAMELYON16 level 0 / 256 (``magnification_range = 256 / downsample``). ``workers``: slides made in
    parallel processes (each holds one slide's memory: peak RSS 0.85–2.84 GB, median 1.42 GB, measured per slide at D = 8 with pcam-cnn). ``features``: compute
    each bundle's feature grid (``True``: ``pcam-cnn``, or an encoder name of
    ``data_tools.features.ENCODERS``). ``no_pixels``: feature-only bundles: once the feature grid is computed
    the RGB tile pools of every level but the coarsest are deleted (``obs_mode="features"`` needs none; a
    fraction of the disk; implies ``features``).

    Shared with ``data_tools dataset`` (:mod:`data_tools.datasets.build`): each slide is made holding its
    bundle's lock and recorded in ``records/NAME.json`` (a failure in ``records/failed/NAME.json`` with its
    reason; the other slides still build; a failed rebuild keeps the previous bundle and record). When
    failures leave the test split with no slide (or no tumour slide) or the set with no slide at all,
    ``HistojaxDataError`` is raised and ``dataset.json`` is not written (a previous one stays). ``shard=(I, N)``: make every N-th of the chosen slides (sorted by
    name) starting at the I-th, so N processes or machines sharing ``out_dir`` (a job array) build disjoint
    slides; ``merge``: make nothing, write ``dataset.json`` from the records. The run that finds every chosen
    slide recorded writes ``dataset.json`` (every recorded slide of the set, its failures under ``failed``).
    Returns the ``dataset.json`` dict plus ``missing`` (chosen slides not yet recorded: ``[]``) and ``run``
    (this run's ``built`` / ``busy`` / ``failed`` names); while slides of other shards are missing, nothing is
    written and the dict holds only ``dataset_written: False``, ``missing``, ``failed`` and ``run``.
    """
    from data_tools.datasets.c16.layout import OWN_TISSUE
    from data_tools.datasets.pcam_bank import pool_rule, split_pools
    from data_tools.features import encoder_record
    from data_tools.ncrf import SHIPPED_DIR, read_ncrf

    out_dir = Path(out_dir)
    d = float(downsample or (SMALL_DOWNSAMPLE if small else FULL_DOWNSAMPLE))
    if not (1 <= d <= 64):
        raise HistojaxDataError(None, f"--downsample {d} must be between 1 and 64 (CAMELYON16 level-0 px per px)")
    encoder = features if isinstance(features, str) else "pcam-cnn" if features or no_pixels else None
    # a built-in name, or your own module:function, probed (a broken one refused) before any slide is made
    encoder_info = encoder_record(encoder) if encoder is not None else {"encoder": None}
    mag = COARSEST / d
    source = annotations or SHIPPED_DIR
    inputs = check_known_inputs(annotations=annotations, patches=patches)  # the published tables' bytes?
    for line in differing_lines(inputs):
        print(line, file=sys.stderr)  # a warning, not a refusal: other inputs are allowed
    every = read_ncrf(source)  # the whole set: its split and donors hold for any subset
    universe = [n for n in every if n in SMALL_SLIDES] if small else list(every)
    if small and len(universe) != len(SMALL_SLIDES):
        raise HistojaxDataError(
            source,
            f"the small variant needs {', '.join(SMALL_SLIDES)}; missing {sorted(set(SMALL_SLIDES) - set(universe))}",
        )
    if names is not None and set(names) - set(universe):
        raise HistojaxDataError(
            source,
            f"no such slide(s) {sorted(set(names) - set(universe))}" + (" in the small variant" if small else ""),
        )
    tumours_all = [n for n in universe if every[n].is_tumour_slide]
    normals_all = [n for n in universe if not every[n].is_tumour_slide]
    donors = {}
    for n in tumours_all:
        if n not in OWN_TISSUE:
            if not normals_all:
                raise HistojaxDataError(
                    source, f"{n} needs a Normal_* slide to lend it tissue; the annotations hold none"
                )
            donors[n] = donor_for(n, tumours_all, normals_all)
    train_all, test_all = split_slides(universe, donors, test_fraction, seed)
    chosen = set(names) if names is not None else set(tumours_all[:n_tumour]) | set(normals_all[:n_normal])
    todo = [n for n in universe if n in chosen]
    side = {n: "test" if n in test_all else "train" for n in universe}
    fold_plan = None  # --folds K: K folds over the train side, a tumour slide with its tissue donor, by label
    if folds is not None:
        from data_tools.datasets.split import folds_record, kfold_split

        group = {n: donors.get(n, n) for n in train_all}
        fold_plan = folds_record(
            kfold_split(train_all, {n: int(every[n].is_tumour_slide) for n in train_all}, folds, seed, group),
            folds,
            seed,
            "train",
            "a tumour slide with the normal slide lending it tissue",
        )
    bank = load_bank(patches)
    train_pool, test_pool = split_pools(bank)
    test_bank = load_bank(test_patches) if test_patches is not None else test_pool
    pools = {
        **pool_rule(),
        "bank": bank.source,
        "train": {
            "source": train_pool.source,
            "patches": len(train_pool),
            "tumour_patches": int(train_pool.labels.sum()),
        },
        "test": {
            "source": test_bank.source,
            "patches": len(test_bank),
            "tumour_patches": int(test_bank.labels.sum()),
            "other_patch_set": test_patches is not None,
        },
    }
    dataset = {
        "kind": "histojax true-scale CAMELYON16 benchmark (data_tools c16)",
        "format": DATASET_FORMAT,
        "note": PIXELS_NOTE,
        "licence": LICENCE,
        "scale": {
            "downsample_from_camelyon16_level0": d,
            "mpp": C16_MPP * d,
            "view_px": TILE_SIZE,
            "view_um": TILE_SIZE * C16_MPP * d,
            "magnification_range": mag,
            "coarsest_downsample_from_level0": COARSEST,
            "level_sets": list(LEVEL_SETS),
        },
        "seed": int(seed),
        "test_fraction": test_fraction,
        "tile_size": TILE_SIZE,
        "annotations": str(source),
        "slides_in_annotations": len(universe),
        "patches": bank.source,
        "patch_pools": pools,
        "split_rule": "by slide, over every slide of the annotations (a subset keeps the whole set's split); "
        "a tumour slide and the normal slide lending it tissue are on the same side; "
        f"at most {test_fraction:.0%} of the tumour and of the normal slides in test; "
        "train slides are textured from the training patch pool only, test slides from the "
        "test pool (or --test-patches) only",
        "inputs": inputs,  # per .tar.gz input given: its sha256 and whether it is the published tables'
        **encoder_info,
        "pixels_kept": not no_pixels,  # encoder (its name); your own's version and spec too
    }
    set_key = {k: dataset[k] for k in (*_SAME_SET_KEYS, "encoder_version") if k in dataset}
    from data_tools.datasets.build import collect_records, run_summary, write_dataset_index
    from data_tools.datasets.split import fold_lists, shard_names

    out_dir.mkdir(parents=True, exist_ok=True)
    _adopt_old_records(out_dir, set_key, universe)
    removed = clean_stale(out_dir)
    if removed and progress:
        print(f"removed {len(removed)} stale temporaries of an interrupted run: {', '.join(removed[:5])}")
    t0 = time.perf_counter()
    mine = [] if merge else shard_names(todo, shard)
    jobs = [
        (
            out_dir,
            every[n],
            every.get(donors.get(n)),
            d,
            slide_seed(seed, n),
            jpeg_quality,
            mag,
            encoder,
            no_pixels,
            side[n],
            set_key,
        )
        for n in mine
    ]
    banks = {"train": train_pool, "test": test_bank}
    bar = tqdm(total=len(jobs), desc="c16 slides", unit="slide", disable=not progress or not jobs)
    results = []
    if workers <= 1 or len(jobs) <= 1:
        _init_worker(banks, progress)
        for job in jobs:
            results.append(_locked_slide(job))
            bar.update(1)
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(
            workers, mp_context=multiprocessing.get_context("fork"), initializer=_init_worker, initargs=(banks, False)
        ) as pool:
            for res in pool.map(_locked_slide, jobs):
                results.append(res)
                bar.update(1)
    bar.close()
    run = {"shard": list(shard) if shard else None, "merge": bool(merge), **run_summary(results)}
    found, failed, missing = collect_records(out_dir, universe, current=lambda r: r.get("settings") == set_key)
    missing = [n for n in missing if n in chosen]
    if missing:
        return {"dataset_written": False, "missing": missing, "failed": failed, "run": run}
    from data_tools.datasets.build import check_scorable

    # failures (a rebuild that failed keeps the previous bundle, not of this set) may leave the test split
    # unscorable: then the previous dataset.json stays as it was (one line, nothing written)
    planned = {
        n: {"split": side[n], "label": int(every[n].is_tumour_slide)}
        for n in universe
        if n in chosen or n in found or n in failed
    }
    check_scorable(out_dir, {"slides": planned}, found, failed)
    if failed and not found:
        why = "; ".join(f"{n}: {failed[n]}" for n in sorted(failed)[:2])[:300]
        raise HistojaxDataError(
            out_dir,
            f"no slide of this set is built: {len(failed)} failed ({why}); dataset.json "
            "not written (previous bundles are kept): fix them and rerun",
        )
    records = [found[n] for n in universe if n in found]
    present = [r["name"] for r in records]
    dataset.update(
        {
            "variant": ("small" if small else "full") if set(present) == set(universe) else "subset",
            "train": [f"bundles/{n}" for n in present if side[n] == "train"],
            "test": [f"bundles/{n}" for n in present if side[n] == "test"],
            "labels": {n: int(every[n].is_tumour_slide) for n in present},
            "failed": dict(sorted(failed.items())),
            "slides": records,
            **({"folds": fold_lists(fold_plan, present)} if fold_plan else {}),
            "seconds_this_run": round(time.perf_counter() - t0, 2),
            "peak_rss_bytes_this_run": max(
                [resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024]
                + [r.get("peak_rss_bytes", 0) for r in records if r["name"] in mine]
            ),
            "workers": int(workers),
            "disk_bytes": {
                "slides": sum(r["tiff_bytes"] for r in records),
                "bundles": sum(r["bundle_bytes"] for r in records),
            },
            "device_bytes": {
                "pixels": sum(r["device_bytes_pixels"] for r in records),
                "features": sum(r["device_bytes_features"] or 0 for r in records),
            },
        }
    )
    write_dataset_index(out_dir, dataset)
    return {**dataset, "missing": [], "run": run}


_SAME_SET_KEYS = ("format", "scale", "seed", "test_fraction", "annotations", "patch_pools", "encoder", "pixels_kept")


__all__ = [
    "FULL_DOWNSAMPLE",
    "SMALL_DOWNSAMPLE",
    "SMALL_SLIDES",
    "clean_stale",
    "make_c16_dataset",
    "make_slide",
    "split_slides",
]
