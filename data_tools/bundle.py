"""Slide bundles: one folder with ``metadata.json`` and ``.npy`` arrays, written atomically.

A bundle holds, for each zoom level the environment may use (``metadata["levels"]``
lists them finest first):
  * ``pixels_KK.npy``  — ``(H, W, 3)`` uint8 RGB of that level,
  * ``tumour_KK.npy``  — ``(H, W)`` uint8 0/1 tumour mask (exclusion holes removed),
and ``tissue.npy`` (bool, coarsest level) and ``annotations.geojson`` (level-0 px).
A *region* bundle (``build_bundle(..., region=...)``) covers one rectangle of the slide only:
its level-0 px are the region's (annotations translated by ``(-x0, -y0)`` and clipped), and
``region.npy`` (bool, coarsest level) marks where a view centre may start (inside a polygon
region); ``metadata["region"]`` records the box in slide px and the kind.
A *tiled* bundle (``storage="tiled"``, format version 2, for gigapixel slides) stores each level as a
pool of tiles with an index grid instead (see :mod:`data_tools.tiled`); ``metadata["storage"]`` says which.
Levels are at downsamples ``R ** (k / (n - 1))`` for each requested level count
``n`` (3 / 5 / 7) and magnification range ``R``, so one bundle serves Easy,
Medium and Hard. Arrays are read with ``allow_pickle=False``; every file's
SHA-256 is recorded and checked on load.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from data_tools.bundle_files.format import (  # noqa: F401  (re-exported: the format's names, as before)
    ANNOTATIONS,
    FEATURES_COMMAND,
    FORMAT_VERSION,
    LEVEL_SETS,
    MAX_FLAT_PIXELS,
    METADATA,
    READ_VERSIONS,
    REGION,
    STORAGES,
    TILED_FORMAT_VERSION,
    TISSUE,
    bundle_downsamples,
    default_magnification_range,
    device_bytes,
    level_device_bytes,
    level_downsamples,
    level_files,
    level_size,
    sha256,
)
from data_tools.bundle_files.reading import Bundle, load_bundle, read_metadata
from data_tools.bundle_files.seals import write_metadata
from data_tools.bundle_files.writes import TEMP_MARKER, as_disk_full, atomic_folder, check_replaceable
from data_tools.errors import BundleError, SlideError
from data_tools.raster import pad, resample


@dataclass(frozen=True)
class Region:
    """A rectangle of the slide a bundle covers: ``box = (x0, y0, x1, y1)`` in level-0 slide px;
    ``polygon`` (slide px) limits it further when ``kind == "polygon"``."""

    box: tuple[int, int, int, int]
    kind: str  # "rectangle", "polygon" or "group"
    polygon: object = None  # shapely (Multi)Polygon for kind "polygon"
    group: str | None = None  # the annotation group/label of kind "group"
    margin: float = 0.0

    @property
    def width(self) -> int:
        return self.box[2] - self.box[0]

    @property
    def height(self) -> int:
        return self.box[3] - self.box[1]


def _group_geometry(name: str, annotations_path, label_map, ann):
    """Union of the polygons of an annotation label (``tumour``/``exclusion``/``tissue``), a group that the
    label map sends to one, or an unmapped group name (case-insensitive)."""
    import shapely

    from data_tools.annotations import LABELS, _is_xml, _resolve_label_map, parse_asap_xml, parse_geojson

    if annotations_path is None:
        raise BundleError(None, f"region group {name!r} needs an annotation file (--annotations)")
    label = _resolve_label_map(label_map).get(name.strip().lower())
    if label in ("tumour", "exclusion", "tissue") and ann is not None:
        if getattr(ann, label).is_empty:
            raise BundleError(
                annotations_path, f"region group {name!r}: the annotation has no {label} polygon inside the slide"
            )
        return getattr(ann, label)
    parse = parse_asap_xml if _is_xml(annotations_path) else parse_geojson
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        items = parse(annotations_path, label_map)
    wanted = {f"unknown:{name}".lower(), str(label).lower()} if label in LABELS else {f"unknown:{name}".lower()}
    polys = [p for lab, p in items if lab.lower() in wanted]
    if not polys:
        raise BundleError(annotations_path, f"region group {name!r}: no polygon in that group or label")
    return shapely.union_all(polys)


def resolve_region(
    region,
    slide_size: tuple[int, int],
    annotations_path=None,
    label_map=None,
    ann=None,
    margin: float = 0.0,
    tile_size: int = 1,
    where=None,
) -> Region:
    """Turn ``region`` into a :class:`Region` clipped to the slide.

    ``region`` is ``(x0, y0, x1, y1)`` in level-0 px, a shapely (Multi)Polygon in level-0 px, or the
    name of an annotation group/label (e.g. ``"tissue"``, ``"tumour"``) whose union's bounding box is
    the region. ``margin`` (level-0 px) grows the box (and buffers a polygon). The region must hold
    one ``tile_size`` view at level 0 after clipping.
    """
    import shapely
    from shapely.geometry.base import BaseGeometry

    polygon, group = None, None
    if isinstance(region, str):
        kind, group = "group", region
        bounds = _group_geometry(region, annotations_path, label_map, ann).bounds
    elif isinstance(region, BaseGeometry):
        kind = "polygon"
        polygon = shapely.make_valid(region) if not region.is_valid else region
        if margin:
            polygon = polygon.buffer(margin)
        polygon = shapely.intersection(polygon, shapely.box(0, 0, *slide_size))
        if polygon.is_empty or polygon.area <= 0:
            raise BundleError(where, f"region polygon has no area inside the slide {slide_size[0]}×{slide_size[1]}")
        bounds = polygon.bounds
    else:
        try:
            bounds = tuple(float(v) for v in region)
        except (TypeError, ValueError):
            bounds = ()
        if (
            len(bounds) != 4
            or not all(math.isfinite(v) for v in bounds)
            or bounds[2] <= bounds[0]
            or bounds[3] <= bounds[1]
        ):
            raise BundleError(
                where,
                f"region {region!r} must be (x0, y0, x1, y1) with x0 < x1 and y0 < y1 "
                "(level-0 px), a shapely polygon, or an annotation group name",
            )
        kind = "rectangle"
    if kind != "polygon":
        bounds = (bounds[0] - margin, bounds[1] - margin, bounds[2] + margin, bounds[3] + margin)
    x0, y0 = max(0, math.floor(bounds[0])), max(0, math.floor(bounds[1]))
    x1, y1 = min(slide_size[0], math.ceil(bounds[2])), min(slide_size[1], math.ceil(bounds[3]))
    if x1 - x0 < tile_size or y1 - y0 < tile_size:
        raise BundleError(
            where,
            f"region ({x0}, {y0}, {x1}, {y1}) inside the slide {slide_size[0]}×{slide_size[1]} "
            f"is smaller than one {tile_size}-px view; choose a larger region",
        )
    return Region(box=(x0, y0, x1, y1), kind=kind, polygon=polygon, group=group, margin=float(margin))


def _crop_annotations(ann, region: Region):
    """``ann`` translated into the region's px and clipped to it (and to its polygon)."""
    import dataclasses as _dc

    import shapely
    from shapely.affinity import translate

    from data_tools.annotations import _as_multipolygon

    x0, y0, x1, y1 = region.box
    clip = region.polygon if region.polygon is not None else shapely.box(x0, y0, x1, y1)
    moved = {
        name: _as_multipolygon(translate(shapely.intersection(getattr(ann, name), clip), -x0, -y0))
        for name in ("tumour", "exclusion", "tissue")
    }
    return _dc.replace(ann, **moved)


def build_bundle(
    slide_path,
    out_dir,
    annotations_path=None,
    level_sets=LEVEL_SETS,
    tile_size: int = 128,
    magnification_range: float | None = None,
    label_map: dict[str, str] | None = None,
    overwrite: bool = False,
    progress: bool = True,
    max_decode_bytes: int | None = None,
    region=None,
    region_margin: float = 0.0,
    storage: str = "dense",
    share_background: bool = True,
    band_bytes: int | None = None,
    reader: str | None = None,
    mpp: float | None = None,
    stated_scale_checked: bool = True,
) -> Path:
    """Build a slide bundle at ``out_dir`` from a slide file and an optional annotation file.

    ``tile_size`` is the view size in px (the env observes ``tile_size × tile_size``
    px of the current level). ``level_sets`` are the scenario level counts to
    support (3 = Easy, 5 = Medium, 7 = Hard). ``magnification_range`` is the
    coarsest downsample (default: :func:`default_magnification_range`).
    Written to a temporary sibling folder and renamed into place, so a crash
    leaves nothing that looks like a bundle. Returns the bundle path.

    ``region`` restricts the bundle to part of the slide (see :func:`resolve_region`): a rectangle
    ``(x0, y0, x1, y1)`` in level-0 px, a shapely polygon (pixels outside it painted white, tissue
    and tumour masked, starts only with the view centre inside it), or an annotation group/label
    name whose union's bounding box is the region; ``region_margin`` grows it (level-0 px). The
    bundle's level-0 px are then the region's, its magnification range is computed for the region.

    ``storage``: ``"dense"`` (default; whole levels as arrays), ``"tiled"`` (tile pools with index grids,
    background tiles sharing one blank tile, built streaming in bands with bounded memory; format
    version 2, see :mod:`data_tools.tiled`) or ``"auto"`` (tiled when the dense levels would need more
    than 256 MiB on the device). ``share_background=False`` keeps every tile of a tiled bundle (exactly
    the dense pixels); ``band_bytes`` bounds the RGB bytes of one band (default 96 MiB).

    ``reader``: what reads the slide (:data:`data_tools.slide_files.open.READERS`: ``"auto"``, the default; ``"native"``;
    ``"openslide"``, any slide through OpenSlide 4).

    ``mpp``: the slide's µm per level-0 px, for a file that states none or a wrong one (``--mpp``); recorded in
    ``metadata["source"]`` as ``mpp`` with ``mpp_from`` ``"given"`` and the file's own value as ``mpp_in_file``.
    Without it the file's own µm/px must lie in :data:`MPP_RANGE` (:func:`check_stated_mpp`);
    ``stated_scale_checked=False`` only for the project's own semi-synthetic slides
    (:mod:`data_tools.datasets.synth`), whose µm/px is a geometry scale that may pass 100 on a small canvas.
    """
    slide_path, out_dir = Path(slide_path), Path(out_dir)
    check_mpp(out_dir, mpp)
    if out_dir.exists() and not overwrite:
        raise BundleError(out_dir, "already exists; pass overwrite=True (--overwrite) to replace it")
    check_replaceable(out_dir)
    if tile_size < 8:
        raise BundleError(out_dir, f"tile size {tile_size} px is too small (minimum 8)")
    if magnification_range is not None and not (math.isfinite(magnification_range) and magnification_range >= 1):
        raise BundleError(
            out_dir, f"magnification range {magnification_range} must be a finite number >= 1 (the coarsest downsample)"
        )
    level_sets = tuple(sorted(set(int(n) for n in level_sets)))
    if storage not in STORAGES:
        raise BundleError(out_dir, f"storage must be one of {STORAGES}, got {storage!r}")
    if not math.isfinite(region_margin):
        raise BundleError(out_dir, f"region margin {region_margin} must be a finite number of level-0 px")
    if band_bytes is not None and not band_bytes > 0:
        raise BundleError(out_dir, f"band bytes {band_bytes} must be a positive number")
    for parent in out_dir.parents:
        if parent.exists() and not parent.is_dir():
            raise BundleError(out_dir, f"cannot create the bundle here: {parent} is a file, not a folder")
    try:
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        lock = build_lock(out_dir)
        lock.__enter__()
    except OSError as e:
        raise BundleError(out_dir, f"cannot create the bundle here ({e.strerror or e})") from None
    try:
        if out_dir.exists() and not overwrite:  # checked again under the lock: another build may have finished
            raise BundleError(out_dir, "already exists; pass overwrite=True (--overwrite) to replace it")
        check_replaceable(out_dir)
        remove_stale_builds(out_dir)
        from data_tools.peak_memory import PeakRSS

        # the build's own peak memory, not the process's (earlier work in a long process does not count)
        with atomic_folder(out_dir) as tmp, PeakRSS() as peak:
            tmp.mkdir(exist_ok=True)
            _build_into(
                tmp,
                slide_path,
                out_dir,
                annotations_path,
                level_sets,
                tile_size,
                magnification_range,
                label_map,
                progress,
                max_decode_bytes,
                region,
                region_margin,
                storage,
                share_background,
                band_bytes,
                reader,
                mpp,
                peak,
                stated_scale_checked=stated_scale_checked,
            )
        return out_dir
    except OSError as e:
        e = as_disk_full(e) or e  # numpy's short write ("N requested and M written"): the disk is full
        raise BundleError(
            out_dir, f"cannot write the bundle ({e.strerror or e}" + (f": {e.filename}" if e.filename else "") + ")"
        ) from None
    finally:
        lock.__exit__(None, None, None)


def _build_into(
    tmp: Path,
    slide_path: Path,
    out_dir: Path,
    annotations_path,
    level_sets,
    tile_size,
    magnification_range,
    label_map,
    progress,
    max_decode_bytes,
    region,
    region_margin,
    storage,
    share_background,
    band_bytes,
    reader=None,
    mpp=None,
    peak=None,
    stated_scale_checked: bool = True,
) -> None:
    """The body of :func:`build_bundle`: write the bundle into ``tmp`` (called with the build lock held, inside
    :func:`data_tools.bundle_files.writes.atomic_folder`, which renames it to ``out_dir`` or removes it)."""
    import shapely.geometry

    from data_tools.annotations import annotations_to_geojson, load_annotations
    from data_tools.masks import rasterize, tissue_mask
    from data_tools.slide_files.base import MAX_DECODE_BYTES
    from data_tools.slide_files.open import open_slide

    with open_slide(slide_path, reader) as reader:
        mpp_in_file = reader.mpp
        if mpp is not None:  # the user's µm/px for a file that states none or a wrong one
            reader.mpp = float(mpp)
        elif stated_scale_checked:  # the file's own µm/px: within the range a given --mpp must be in
            check_stated_mpp(slide_path, reader.mpp)
        width0, height0 = reader.dimensions
        ann = None
        if annotations_path is not None:
            ann = load_annotations(annotations_path, label_map=label_map, slide_size=(width0, height0))
        reg = None
        if region is not None:
            reg = resolve_region(
                region,
                (width0, height0),
                annotations_path,
                label_map,
                ann,
                margin=region_margin,
                tile_size=tile_size,
                where=slide_path,
            )
            width0, height0 = reg.width, reg.height
            if ann is not None:
                ann = _crop_annotations(ann, reg)
        r = magnification_range or default_magnification_range(width0, height0, tile_size)
        downsamples = bundle_downsamples(level_sets, r)
        sizes = [level_size(width0, height0, d) for d in downsamples]
        check_zoom(slide_path, (width0, height0), downsamples, sizes, tile_size)
        total = sum(max(w, tile_size) * max(h, tile_size) for w, h in sizes)
        if storage == "auto":
            from data_tools.tiled import AUTO_TILED_BYTES

            dense_bytes = sum(device_bytes(max(w, tile_size), max(h, tile_size)) for w, h in sizes)
            storage = "tiled" if dense_bytes > AUTO_TILED_BYTES else "dense"
        build_stats = None
        if storage == "tiled":
            from data_tools.tiled import BAND_BYTES, build_tiled_levels

            levels_meta, build_stats = build_tiled_levels(
                reader,
                tmp,
                downsamples,
                sizes,
                tile_size,
                ann=ann,
                reg=reg,
                share_background=share_background,
                band_bytes=band_bytes or BAND_BYTES,
                progress=progress,
                mpp=reader.mpp,
            )
        elif total > MAX_FLAT_PIXELS:
            raise BundleError(
                slide_path,
                f"the {len(sizes)} levels would hold {total:,} px "
                f"({total * 7 / 2**30:.1f} GiB on the device with their masks), more than the "
                f"{MAX_FLAT_PIXELS:,} px one dense slide array can index: use fewer levels "
                "(--levels), a larger --magnification-range start, or a coarser slide",
            )
        if storage == "dense":
            levels_meta = []
        cache: tuple[int, np.ndarray] | None = None
        bar = tqdm(
            downsamples if storage == "dense" else [],
            desc=f"building {out_dir.name}",
            unit="level",
            disable=not progress or storage != "dense",
        )
        for k, d in enumerate(bar):
            # the coarsest source level that is still at least as fine as the target
            src = max(
                (i for i, lv in enumerate(reader.levels) if lv.downsample <= d * (1 + 1e-6)),
                key=lambda i: reader.levels[i].downsample,
            )
            ds = reader.levels[src].downsample
            if cache is None or cache[0] != src:
                cache = None  # free the previous level before decoding the next
                if reg is None:
                    cache = (src, reader.read_level(src, max_bytes=max_decode_bytes or MAX_DECODE_BYTES))
                else:  # only the region's window of the source level
                    win = (
                        math.floor(reg.box[0] / ds),
                        math.floor(reg.box[1] / ds),
                        math.ceil(reg.box[2] / ds),
                        math.ceil(reg.box[3] / ds),
                    )
                    needed = (win[2] - win[0]) * (win[3] - win[1]) * 3
                    if needed > (max_decode_bytes or MAX_DECODE_BYTES):
                        raise BundleError(
                            slide_path,
                            f"region window of level {src} needs {needed:,} bytes, "
                            "over the decode limit; use a smaller region",
                        )
                    cache = (src, reader.read_region(src, win[0], win[1], win[2] - win[0], win[3] - win[1]))
            size = level_size(width0, height0, d)
            offset = (
                (0.0, 0.0)
                if reg is None
                else (reg.box[0] / ds - math.floor(reg.box[0] / ds), reg.box[1] / ds - math.floor(reg.box[1] / ds))
            )
            content = resample(cache[1], ds, d, size, offset)
            inside = None
            if reg is not None and reg.polygon is not None:
                from shapely.affinity import translate

                inside = rasterize(translate(reg.polygon, -reg.box[0], -reg.box[1]), size[0], size[1], d)
                content = content.copy()
                content[~inside] = 255  # outside the polygon: glass
            pixels = pad(content, tile_size, 255)
            tumour = np.zeros(size[::-1], dtype=bool)
            if ann is not None:
                tumour = rasterize(ann.tumour, size[0], size[1], d)
            tumour = pad(tumour.astype(np.uint8), tile_size, 0)
            names = level_files(k)
            np.save(tmp / names["pixels"], pixels, allow_pickle=False)
            np.save(tmp / names["tumour"], tumour, allow_pickle=False)
            levels_meta.append(
                {
                    "downsample": d,
                    "width": int(pixels.shape[1]),
                    "height": int(pixels.shape[0]),
                    "content_width": size[0],
                    "content_height": size[1],
                    "mpp": None if reader.mpp is None else reader.mpp * d,
                    "tumour_pixels": int(tumour.sum()),
                    **names,
                }
            )
            if k == len(downsamples) - 1:
                tissue = tissue_mask(pixels[: size[1], : size[0]])
                if inside is not None:
                    tissue &= inside
                np.save(tmp / TISSUE, pad(tissue, tile_size, False), allow_pickle=False)
                if reg is not None:  # where a view centre may start
                    allowed = inside if inside is not None else np.ones(size[::-1], dtype=bool)
                    np.save(tmp / REGION, pad(allowed, tile_size, False), allow_pickle=False)
        cache = None
        geojson = annotations_to_geojson(ann) if ann is not None else {"type": "FeatureCollection", "features": []}
        (tmp / ANNOTATIONS).write_text(json.dumps(geojson, allow_nan=False))
        files = sorted(p.name for p in tmp.iterdir() if p.name != TEMP_MARKER)  # not the temporary's marker
        if build_stats is not None and peak is not None:  # recorded as the build's peak (data_tools.peak_memory)
            peak.stop()
            build_stats.update(peak_rss_bytes=peak.bytes, peak_rss_method=peak.method)
        metadata = {
            "format_version": FORMAT_VERSION if storage == "dense" else TILED_FORMAT_VERSION,
            "storage": storage,
            "device_bytes": sum(level_device_bytes(lv) for lv in levels_meta),
            **({} if build_stats is None else {"build": build_stats}),
            "source": {
                "file": slide_path.name,
                "sha256": sha256(slide_path),
                "format": reader.format,
                "width": width0,
                "height": height0,
                "mpp": reader.mpp,
                **({} if mpp is None else {"mpp_from": "given", "mpp_in_file": mpp_in_file}),
            },
            "annotations": None
            if annotations_path is None
            else {
                "file": Path(annotations_path).name,
                "sha256": sha256(Path(annotations_path)),
                "unknown_groups": list(ann.unknown_groups),
                "n_polygons": dict(ann.n_polygons),
                "tumour_area_px": float(ann.tumour.area),
            },
            "label_map": label_map or {},
            "tile_size": tile_size,
            "magnification_range": r,
            "level_sets": list(level_sets),
            "levels": levels_meta,
            "tissue": {"file": TISSUE, "level": len(levels_meta) - 1},
            "region": None
            if reg is None
            else {
                "box": list(reg.box),
                "kind": reg.kind,
                "group": reg.group,
                "margin": reg.margin,
                "polygon": None if reg.polygon is None else shapely.geometry.mapping(reg.polygon),
                "mask": REGION,
                "level": len(levels_meta) - 1,
            },
            "checksums": {name: sha256(tmp / name) for name in files},
        }
        write_metadata(tmp, metadata)


def check_zoom(
    where, size0: tuple[int, int], downsamples: list[float], sizes: list[tuple[int, int]], tile_size: int
) -> None:
    """Refuse level choices with which zooming would do nothing: a single level (magnification range 1, or a
    slide smaller than one view), or two levels of the same size once padded to one ``tile_size`` view
    (a range so large that the coarse levels shrink below one view)."""
    if len(downsamples) < 2:
        hint = (
            f"the slide ({size0[0]}×{size0[1]} px) is smaller than two {tile_size}-px views: use a smaller --tile-size"
            if min(size0) < 2 * tile_size
            else "use a --magnification-range above 1"
        )
        raise BundleError(where, f"magnification range {downsamples[-1]:g} gives a single zoom level; {hint}")
    padded = [(max(w, tile_size), max(h, tile_size)) for w, h in sizes]
    for (d0, p0), (d1, p1) in zip(zip(downsamples, padded), zip(downsamples[1:], padded[1:])):
        if p0 == p1:
            best = default_magnification_range(*size0, tile_size)
            raise BundleError(
                where,
                f"levels at downsample {d0:.4g} and {d1:.4g} are both {p1[0]}×{p1[1]} px once "
                f"padded to one {tile_size}-px view, so zooming between them does nothing; use a "
                f"--magnification-range of at most {best:g} or a smaller --tile-size",
            )


def _lock_path(out_dir: Path) -> Path:
    return out_dir.parent / f".{out_dir.name}.lock"


@contextlib.contextmanager
def build_lock(out_dir):
    """Hold an exclusive ``fcntl.flock`` on the hidden file ``.NAME.lock`` beside ``out_dir`` while building it,
    so concurrent builds of one bundle (processes sharing a cache) run one after another. The holder removes
    the lock file when done; a waiter that then holds a removed file opens the new one. The kernel drops the
    lock of a killed process. Filesystems without ``flock`` are built on unlocked."""
    import fcntl

    path = _lock_path(Path(out_dir))
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                warnings.warn(f"{out_dir}: another process is building it; waiting for it to finish", stacklevel=3)
                fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError as e:
            if isinstance(e, BlockingIOError) or e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                os.close(fd)
                raise
            break  # no locking on this filesystem
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)  # the previous holder removed this lock file: take the new one
    try:
        yield path
    finally:
        try:
            os.unlink(path)
        except OSError:
            pass
        os.close(fd)


def remove_stale_builds(out_dir) -> list[Path]:
    """Remove the hidden ``.NAME.tmp-*`` / ``.NAME.old-*`` folders beside ``out_dir`` left by builds that were
    killed (call it holding :func:`build_lock`: every live build of ``out_dir`` holds it, so any such folder
    belongs to a dead one) — only folders histojax marked as its temporaries
    (:func:`data_tools.bundle_files.writes.is_our_temporary`; a user's file or folder of that name stays) — and the
    leftovers of killed builds of other names beside it that no live process holds
    (:func:`data_tools.datasets.locks.clean_stale_builds`). Returns the paths removed."""
    from data_tools.bundle_files.writes import remove_temporary
    from data_tools.datasets.locks import clean_stale_builds

    out_dir = Path(out_dir)
    stale = [p for kind in ("tmp", "old") for p in out_dir.parent.glob(f".{glob.escape(out_dir.name)}.{kind}-*")]
    stale = [p for p in stale if remove_temporary(p)]
    others = clean_stale_builds(out_dir.parent, keep=(out_dir.name,))  # killed builds of other names
    return stale + [out_dir.parent / n.split(" (")[0] for n in others]


MPP_RANGE = (0.01, 100.0)
"""µm per level-0 px a given ``--mpp`` may be (scanners: ~0.1 to ~10; outside it, likely nm or mm)."""


def check_mpp(where, mpp) -> None:
    """Refuse (:class:`BundleError` naming ``where``) a given µm/px that is not a number within :data:`MPP_RANGE`;
    None (not given) passes."""
    if mpp is None:
        return
    try:
        value = float(mpp)
    except (TypeError, ValueError):
        value = float("nan")
    if not (math.isfinite(value) and MPP_RANGE[0] <= value <= MPP_RANGE[1]):
        raise BundleError(
            where,
            f"--mpp {mpp!r} is not a µm per level-0 px between {MPP_RANGE[0]:g} and "
            f"{MPP_RANGE[1]:g} (0.25 at 40x, 0.5 at 20x): micrometres per pixel, not nm or mm",
        )


def check_stated_mpp(slide_path, mpp) -> None:
    """Refuse (:class:`~data_tools.errors.SlideError` naming the slide file, one line) a µm/px the slide file
    itself states (TIFF resolution, SVS ``MPP``, OME ``PhysicalSizeX``, OpenSlide's ``mpp-x``, DICOM pixel
    spacing) outside :data:`MPP_RANGE`, the range a given ``--mpp`` must lie in; None (the file states none)
    passes. The way out is the true scale given with ``--mpp``, which replaces the file's (so this is checked
    only when none is given)."""
    if mpp is None:
        return
    value = float(mpp)
    if not (math.isfinite(value) and MPP_RANGE[0] <= value <= MPP_RANGE[1]):
        raise SlideError(
            slide_path,
            f"the file states {value:g} µm per level-0 px, not between {MPP_RANGE[0]:g} and {MPP_RANGE[1]:g} "
            "(0.25 at 40x, 0.5 at 20x): a wrong scale in the file (nm or mm?); give the true one with --mpp",
        )


def set_mpp(bundle, mpp: float) -> dict:
    """Record ``mpp`` (µm per level-0 px, given by the user) as the bundle's scale: ``source.mpp`` (the file's own
    value kept as ``source.mpp_in_file``, ``mpp_from`` ``"given"``) and each level's ``mpp`` (``mpp × downsample``);
    ``metadata.json`` is rewritten, sealed (its seal checked first). Returns the new metadata."""
    from data_tools.bundle_files.seals import verify_metadata

    bundle = Path(bundle)
    check_mpp(bundle, mpp)
    metadata = dict(read_metadata(bundle))
    verify_metadata(bundle, metadata)  # a hand edit is refused, never resealed
    source = dict(metadata.get("source") or {})
    if source.get("mpp_from") != "given":
        source["mpp_in_file"] = source.get("mpp")
    source.update(mpp=float(mpp), mpp_from="given")
    levels = [{**lv, "mpp": float(mpp) * float(lv["downsample"])} for lv in metadata["levels"]]
    metadata = {**metadata, "source": source, "levels": levels}
    write_metadata(bundle, metadata)
    return metadata


__all__ = [
    "check_mpp",
    "check_stated_mpp",
    "set_mpp",
    "check_zoom",
    "Bundle",
    "FORMAT_VERSION",
    "LEVEL_SETS",
    "STORAGES",
    "TILED_FORMAT_VERSION",
    "level_device_bytes",
    "Region",
    "build_bundle",
    "bundle_downsamples",
    "resolve_region",
    "default_magnification_range",
    "level_downsamples",
    "level_size",
    "load_bundle",
    "read_metadata",
    "build_lock",
    "remove_stale_builds",
]


def drop_pixels(folder) -> int:
    """Delete the RGB tile pools of every level of the tiled bundle at ``folder`` but its coarsest (kept for
    thumbnails), leaving tumour tables, index grids, tissue and feature grids: a feature-only bundle
    (``obs_mode="features"`` needs no pixels; ``obs_mode="pixels"`` is then refused, naming the levels).
    The recorded ``device_bytes`` stay those of the pixel layout. ``metadata.json`` is rewritten first
    (atomically), then the files are deleted, so a crash leaves at most unreferenced files.
    Returns the bytes freed on disk."""
    folder = Path(folder)
    metadata = read_metadata(folder)
    if not metadata.is_tiled:
        raise BundleError(folder, "only tiled bundles can drop their pixels")
    if not metadata.features:
        raise BundleError(
            folder,
            f"has no feature grid; compute one first (`{FEATURES_COMMAND}`), a bundle "
            "without pixels and features is of no use",
        )
    levels, files = [], []
    for k, lv in enumerate(metadata["levels"]):
        lv = dict(lv)
        if k < len(metadata["levels"]) - 1 and lv.get("tiles"):
            files.append(lv["tiles"])
            lv["tiles"] = None
        levels.append(lv)
    checksums = {k: v for k, v in metadata.checksums.items() if k not in files}
    write_metadata(
        folder,
        {
            **metadata,
            "levels": levels,
            "checksums": checksums,
            "pixels_dropped": "RGB tile pools of every level but the coarsest deleted "
            "(feature-only bundle); device_bytes is the pixel layout's",
        },
    )
    freed = 0
    for name in files:
        f = folder / name
        if f.is_file():
            freed += f.stat().st_size
            f.unlink()
    return freed
