"""The slide-bundle format, in one place: schema, file names, versions, device bytes, checksums,
atomic writes and the verified read of every kind of bundle (dense, tiled, feature grids).

Why here, in ``data_tools`` (the lower layer, numpy only): data flows one way. ``data_tools``
(offline: slide readers, shapely, PIL) *writes* bundles; ``histojax`` (the environment, JAX)
*reads* them. Both need the format, and the reader must not pull in the writer nor the writer
JAX, so the format is its own module of the lower package, imported by the writer
(:mod:`data_tools.bundle`, :mod:`data_tools.tiled`, :mod:`data_tools.features`) and by every
reader (:mod:`histojax.core.slide`, :mod:`histojax.render`, :mod:`histojax.cache`); it imports nothing
of either (only the leaf module of error types). Nothing else reads ``metadata.json`` or checks a
checksum.

A bundle is one folder with ``metadata.json`` (:data:`METADATA`) and ``.npy`` arrays. For each
zoom level the environment may use (``metadata["levels"]`` lists them finest first):
  * dense (format version 1): ``pixels_KK.npy`` ``(H, W, 3)`` uint8 RGB and ``tumour_KK.npy``
    ``(H, W)`` uint8 0/1 tumour mask (exclusion holes removed);
  * tiled (format version 2, gigapixel slides): tile pools and index grids per level (see
    :class:`TiledLevel` and :mod:`data_tools.tiled`);
plus ``tissue.npy`` (bool, coarsest level), ``annotations.geojson`` (level-0 px), ``region.npy``
(region bundles) and optional feature grids ``features_KK.npy`` (``metadata["features"]``).
Every file's SHA-256 is recorded in ``metadata["checksums"]`` and checked on load; arrays are read
with ``allow_pickle=False``. :class:`BundleMetadata` is the typed view of ``metadata.json``.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import shutil
import stat
import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.errors import BundleError

FORMAT_VERSION = 1        # dense bundles (pixels_KK.npy / tumour_KK.npy)
TILED_FORMAT_VERSION = 2  # tiled bundles (tile pools + index grids, see data_tools.tiled)
READ_VERSIONS = (FORMAT_VERSION, TILED_FORMAT_VERSION)
STORAGES = ("dense", "tiled", "auto")
METADATA = "metadata.json"
TISSUE = "tissue.npy"
REGION = "region.npy"
ANNOTATIONS = "annotations.geojson"
LEVEL_SETS = (3, 5, 7)
MAX_FLAT_PIXELS = 2**31 // 2  # the env indexes pixels with int32
FEATURES_COMMAND = "python -m data_tools features BUNDLE"


def level_files(k: int) -> dict[str, str]:
    """File names of dense bundle level ``k`` (finest first): ``{"pixels": ..., "tumour": ...}``."""
    return {"pixels": f"pixels_{k:02d}.npy", "tumour": f"tumour_{k:02d}.npy"}


def tiled_level_files(k: int) -> dict[str, str]:
    """File names of tiled bundle level ``k``: tile pool, tile index, SAT pool, SAT index."""
    return {"tiles": f"tiles_{k:02d}.npy", "tile_index": f"tile_index_{k:02d}.npy",
            "sat_tiles": f"sat_tiles_{k:02d}.npy", "sat_index": f"sat_index_{k:02d}.npy"}


# ----------------------------------------------------------------------------- level geometry
def default_magnification_range(width: int, height: int, tile_size: int) -> float:
    """Largest power of two ``R`` such that the slide's shorter side is still at least one view
    (``tile_size`` px) at downsample ``R``: at the coarsest level one view shows most of the slide."""
    shorter = min(width, height)
    r = 1
    while shorter / (r * 2) >= tile_size:
        r *= 2
    return float(r)


def level_downsamples(n_levels: int, magnification_range: float) -> list[float]:
    """Downsamples (level-0 px per level px) of an ``n_levels`` scenario, coarsest first.

    Level ``z`` (0 = coarsest) has downsample ``R ** ((n - 1 - z) / (n - 1))``: the
    same range ``R`` for every scenario, split into equal zoom steps in log scale.
    """
    if n_levels < 2:
        raise ValueError(f"a scenario needs at least 2 zoom levels, got {n_levels}")
    return [float(magnification_range ** ((n_levels - 1 - z) / (n_levels - 1))) for z in range(n_levels)]


def bundle_downsamples(level_sets, magnification_range: float) -> list[float]:
    """The union of the downsamples of all requested level counts, finest first (deduplicated)."""
    found: list[float] = []
    for n in level_sets:
        for d in level_downsamples(n, magnification_range):
            if not any(math.isclose(d, e, rel_tol=1e-9) for e in found):
                found.append(d)
    return sorted(found)


def level_size(width0: int, height0: int, downsample: float) -> tuple[int, int]:
    """(width, height) in px of a level at ``downsample`` of a level-0 ``width0 × height0`` slide."""
    return max(1, int(width0 // downsample)), max(1, int(height0 // downsample))


def device_bytes(width: int, height: int) -> int:
    """Device bytes the env needs for one ``width × height`` px level: RGB uint8 pixels plus the
    int32 summed-area table of its tumour mask."""
    return 3 * width * height + 4 * (width + 1) * (height + 1)


def level_device_bytes(level: dict) -> int:
    """Device bytes of one bundle level from its metadata: dense (:func:`device_bytes`) or tiled (the
    recorded pool and index bytes, see :mod:`data_tools.tiled`)."""
    if level.get("storage") == "tiled":
        return int(level["device_bytes"])
    return device_bytes(level["width"], level["height"])


def grid_shape(width: int, height: int, tile_size: int, stride: int) -> tuple[int, int]:
    """``(gh, gw)``: feature-grid positions of ``tile_size`` views every ``stride`` px inside a
    ``width × height`` px level (``gw = (W − tile_size) // stride + 1``, likewise ``gh``)."""
    if stride < 1:
        raise ValueError(f"stride must be at least 1 px, got {stride}")
    return max(0, (height - tile_size) // stride + 1), max(0, (width - tile_size) // stride + 1)


def level_grids(metadata: dict, stride: int) -> list[tuple[int, int]]:
    """``(gh, gw)`` feature grid of every bundle level (finest first)."""
    t = int(metadata["tile_size"])
    return [grid_shape(int(lv["width"]), int(lv["height"]), t, stride) for lv in metadata["levels"]]


# ----------------------------------------------------------------------------- typed metadata
class LevelMeta(dict):
    """One entry of ``metadata["levels"]`` (a dict, as stored) with typed read access."""

    @property
    def downsample(self) -> float:
        """Level-0 px per px of this level."""
        return float(self["downsample"])

    @property
    def width(self) -> int:
        """Level width in px (padded to at least one view)."""
        return int(self["width"])

    @property
    def height(self) -> int:
        """Level height in px (padded to at least one view)."""
        return int(self["height"])

    @property
    def is_tiled(self) -> bool:
        """True for a tiled level (tile pools instead of dense arrays)."""
        return self.get("storage") == "tiled"

    @property
    def device_bytes(self) -> int:
        """Device bytes of this level (:func:`level_device_bytes`)."""
        return level_device_bytes(self)


class BundleMetadata(dict):
    """``metadata.json`` of a bundle: the JSON object as read (a dict, so ``metadata["key"]`` still
    works and it is written back unchanged) with typed properties for every field readers use."""

    @property
    def format_version(self) -> int:
        """1 dense, 2 tiled."""
        return int(self["format_version"])

    @property
    def storage(self) -> str:
        """``"dense"`` or ``"tiled"``."""
        return self.get("storage", "dense")

    @property
    def is_tiled(self) -> bool:
        return self.storage == "tiled"

    @property
    def tile_size(self) -> int:
        """View size in px."""
        return int(self["tile_size"])

    @property
    def magnification_range(self) -> float:
        """Coarsest downsample ``R`` (level-0 px per px)."""
        return float(self["magnification_range"])

    @property
    def level_sets(self) -> list[int] | None:
        """Scenario level counts the bundle was built for (e.g. ``[3, 5, 7]``)."""
        return self.get("level_sets")

    @property
    def levels(self) -> list[LevelMeta]:
        """Bundle levels, finest first."""
        return [LevelMeta(lv) for lv in self["levels"]]

    @property
    def downsamples(self) -> list[float]:
        """Downsample of every bundle level, finest first."""
        return [float(lv["downsample"]) for lv in self["levels"]]

    @property
    def device_bytes(self) -> int:
        """Device bytes of all bundle levels (as recorded at build time)."""
        return int(self["device_bytes"])

    @property
    def checksums(self) -> dict[str, str]:
        """SHA-256 hex digest of every file, by name."""
        return self["checksums"]

    @property
    def tissue_file(self) -> str:
        """File name of the coarsest level's tissue mask."""
        return self["tissue"]["file"]

    @property
    def region_mask_file(self) -> str | None:
        """File name of the allowed-start mask of a region bundle, else ``None``."""
        region = self.get("region")
        return region.get("mask") if region else None

    @property
    def region(self) -> dict | None:
        """The region record of a region bundle (``box`` in slide px, ``kind``, ``mask``), else ``None``."""
        return self.get("region") or None

    @property
    def region_offset(self) -> tuple[float, float]:
        """Level-0 slide px of the bundle's level-0 px ``(0, 0)``: the region's corner, else ``(0, 0)``."""
        box = (self.region or {}).get("box")
        return (float(box[0]), float(box[1])) if box else (0.0, 0.0)

    @property
    def pixel_levels(self) -> list[int]:
        """Indices of the levels (finest first) whose pixels the bundle holds; the others were dropped
        by :func:`drop_pixels` (feature-only bundles of ``data_tools c16 --no-pixels``)."""
        return [k for k, lv in enumerate(self["levels"]) if lv.get("storage") != "tiled" or lv.get("tiles")]

    @property
    def features(self) -> dict | None:
        """The feature-grid record (encoder, dim, stride, levels, projection), ``None`` without one."""
        return self.get("features") or None

    @property
    def annotations(self) -> dict | None:
        """The annotation source record (file, sha256, tumour_area_px, ...), ``None`` without one."""
        return self.get("annotations") or None

    @property
    def source(self) -> dict:
        """The slide source record (file, sha256, format, width, height, mpp)."""
        return self.get("source") or {}

    @property
    def slide_label(self) -> int:
        """Slide-level label: 1 (tumour) when any tumour was annotated, else 0."""
        return int(float((self.annotations or {}).get("tumour_area_px") or 0.0) > 0.0)

    def with_levels(self, chosen: list[int]) -> "BundleMetadata":
        """A copy holding only bundle levels ``chosen`` (in that order)."""
        return BundleMetadata({**self, "levels": [self["levels"][k] for k in chosen]})


def select_levels(metadata: dict, n_levels: int, where="") -> list[int]:
    """Bundle level indices (finest-first order in the metadata) of an ``n_levels`` scenario, coarsest first."""
    available = [lv["downsample"] for lv in metadata["levels"]]
    chosen = []
    for d in level_downsamples(n_levels, metadata["magnification_range"]):
        match = [k for k, a in enumerate(available) if math.isclose(a, d, rel_tol=1e-6)]
        if not match:
            raise BundleError(where or None, f"bundle has no level at downsample {d:.4g} needed for {n_levels} "
                              f"zoom levels (it was built for {metadata.get('level_sets')}); rebuild with "
                              f"`python -m data_tools build ... --levels {n_levels}`")
        chosen.append(match[0])
    return chosen


def feature_bytes(metadata: dict, chosen: list[int], where=None) -> int:
    """Device bytes of the feature grids of bundle levels ``chosen`` (0 if the bundle has none)."""
    info = metadata.get("features")
    if not info:
        return 0
    itemsize = np.dtype(info.get("dtype", "float32")).itemsize
    try:
        return sum(int(np.prod(info["levels"][k]["grid"])) * int(info["dim"]) * itemsize for k in chosen)
    except (KeyError, IndexError, TypeError):
        raise BundleError(where, "metadata['features'] is malformed; recompute with "
                          "`python -m data_tools features BUNDLE`") from None


def tumour_table_bytes(level: dict, tile_size: int) -> int:
    """Device bytes of one bundle level's tumour table alone (no pixels): the tiled SAT pool and its index
    grid, or the dense level's uint32 summed-area table."""
    if level.get("storage") == "tiled":
        gh, gw = level["grid"]
        return int(level["sat_pool_tiles"]) * (tile_size + 1) ** 2 * 4 + 4 * int(gh) * int(gw)
    return 4 * (int(level["width"]) + 1) * (int(level["height"]) + 1)


def slide_device_bytes(metadata: dict, chosen: list[int], pixels: bool = True, features: bool = False,
                       where=None) -> int:
    """Device bytes of bundle levels ``chosen`` (from the metadata, nothing read): pixels and tumour tables
    (``pixels=False``: tumour tables only), plus the feature grids when ``features``; start weights are
    small (the coarsest level) and not counted."""
    t = int(metadata["tile_size"])
    if pixels:
        needed = sum(level_device_bytes(metadata["levels"][k]) for k in chosen)
        if metadata.get("storage") == "tiled":
            needed += 3 * t ** 2  # the spare tile at the end of the pool
    else:
        needed = sum(tumour_table_bytes(metadata["levels"][k], t) for k in chosen)
    return needed + (feature_bytes(metadata, chosen, where) if features else 0)


# ----------------------------------------------------------------------------- checksums
def sha256(path) -> str:
    """Hex SHA-256 of a file's bytes; of a folder (a DICOM WSI), of its files' names and bytes in name order."""
    h = hashlib.sha256()
    folder = Path(path).is_dir()
    for file in sorted(p for p in Path(path).iterdir() if p.is_file()) if folder else [Path(path)]:
        if folder:
            h.update(file.name.encode() + b"\0")
        with open(file, "rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


def file_digest(path, limit: int = 256 * 2**20) -> str:
    """SHA-256 of a file's content (files over ``limit`` bytes: its size, first and last 16 MiB),
    so a cached bundle is rebuilt when the slide changes without reading gigabytes each time."""
    path = Path(path)
    if path.stat().st_size <= limit:
        return sha256(path)
    h = hashlib.sha256()
    size = path.stat().st_size
    with open(path, "rb") as f:
        h.update(str(size).encode())
        h.update(f.read(16 * 2**20))
        f.seek(size - 16 * 2**20)
        h.update(f.read())
    return h.hexdigest()


def text_digest(text: str | bytes, length: int = 16) -> str:
    """The first ``length`` hex digits of the SHA-256 of ``text`` (a cache key)."""
    return hashlib.sha256(text.encode() if isinstance(text, str) else text).hexdigest()[:length]


# ----------------------------------------------------------------------------- atomic writes
TEMP_MARKER = ".histojax-temporary"
"""The file histojax writes inside every temporary folder it makes (``.NAME.tmp-XXXXXXXX``, ``.NAME.old-XXXXXXXX``):
the cleaners of killed runs delete or rename only folders holding it (:func:`is_our_temporary`); anything else of
that name is the user's and is left alone."""
TEMP_MARKER_TEXT = b"histojax temporary folder: made by a build, removed when it ends or by the next run\n"
TEMP_NAME = re.compile(r"^\..+\.(?:tmp|old)-[0-9A-Za-z]+$")
"""Names of histojax's temporaries (``.NAME.tmp-XXXXXXXX``, ``.NAME.old-XXXXXXXX``); only the marker proves one."""
SHORT_WRITE = "requested and"  # numpy's words for a short write (``N requested and M written``): the disk is full


def mark_temporary(folder) -> Path:
    """Create the folder ``folder`` (and its parents) if absent and write :data:`TEMP_MARKER` inside it: the proof
    that histojax made it as a temporary (see :func:`is_our_temporary`). Returns ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / TEMP_MARKER).write_bytes(TEMP_MARKER_TEXT)
    return folder


def is_our_temporary(path) -> bool:
    """True when ``path`` is a real folder (not a link) holding histojax's :data:`TEMP_MARKER` (a regular file
    with its exact text): a temporary a histojax build made. A plain file, a link or a folder without the
    marker is not, whatever its name."""
    path = Path(path)
    marker = path / TEMP_MARKER
    try:
        if path.is_symlink() or not path.is_dir() or marker.is_symlink() or not marker.is_file():
            return False
        if marker.stat().st_size != len(TEMP_MARKER_TEXT):
            return False
        return marker.read_bytes() == TEMP_MARKER_TEXT
    except OSError:
        return False


def remove_temporary(path) -> bool:
    """Delete the folder ``path`` when :func:`is_our_temporary` proves histojax made it; returns whether it did."""
    if not is_our_temporary(path):
        return False
    shutil.rmtree(path, ignore_errors=True)
    return True


def as_disk_full(e: OSError) -> OSError | None:
    """A short write (numpy's ``N requested and M written``, no errno) as the ``ENOSPC`` it is ("No space left on
    device", the file name kept), else None."""
    import errno

    if e.errno is None and SHORT_WRITE in str(e):
        return OSError(errno.ENOSPC, f"No space left on device ({e})", e.filename)
    return None


@contextlib.contextmanager
def atomic_file(path):
    """Yield a temporary path for ``path``'s new content, inside a hidden marked folder beside it
    (``.NAME.tmp-XXXXXXXX/NAME``, see :func:`mark_temporary`); when the block ends the file there is fsync-ed and
    ``os.replace``-d onto ``path`` (readers never see half a file) and the folder removed. On an error the
    temporary folder is removed and ``path`` is left as it was; an ``OSError`` names ``path`` (not the temporary),
    and a short write (a full disk) says "No space left on device"."""
    path = Path(path)
    folder = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    tmp = folder / path.name
    try:
        mark_temporary(folder)
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        shutil.rmtree(folder, ignore_errors=True)
    except OSError as e:
        shutil.rmtree(folder, ignore_errors=True)
        full = as_disk_full(e)
        if full is not None:
            raise OSError(full.errno, full.strerror, str(path)) from None
        if e.filename is None or str(folder) in str(e.filename):  # name the file written, not its temporary
            raise OSError(e.errno, e.strerror or str(e), str(path)) from None
        raise
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise


def save_array(path, array: np.ndarray) -> None:
    """``np.save`` (no pickles) atomically onto ``path`` (see :func:`atomic_file`)."""
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)


def write_json(path, data) -> None:
    """Write ``data`` as JSON (indent 1) atomically onto ``path`` (see :func:`atomic_file`)."""
    with atomic_file(path) as tmp, open(tmp, "w") as f:
        json.dump(data, f, indent=1, allow_nan=False)


METADATA_DIGEST = "metadata_sha256"  # the SHA-256 of the rest of metadata.json (see metadata_digest)


def metadata_digest(metadata: dict) -> str:
    """Hex SHA-256 of ``metadata`` without its :data:`METADATA_DIGEST` entry, serialised canonically
    (sorted keys, no spaces; floats as Python writes them, which JSON reads back exactly)."""
    body = {k: v for k, v in metadata.items() if k != METADATA_DIGEST}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":"),  # json-not-written (a digest)
                                     allow_nan=True).encode()).hexdigest()


DATASET_DIGEST = "dataset_sha256"
"""Key of ``dataset.json``'s seal (``histojax dataset``, ``c16``): the SHA-256 of the rest (as :func:`metadata_digest`)."""
MAX_DATASET_JSON_BYTES = 256 << 20  # bytes: far above any cohort's index (a few hundred bytes per slide); read, it
# takes about 4.4× its size (a 200 MB file peaked at 885 MB RSS)


SEALING_KINDS = ("histojax dataset of real slides (data_tools dataset)",
                 "histojax true-scale CAMELYON16 benchmark (data_tools c16)")
"""``kind`` of the ``dataset.json`` files ``histojax dataset`` and ``c16`` write, sealed since 2026-11; one of them
without a seal is an older build or a seal removed by hand (a warning says so once per file)."""
_UNSEALED_WARNED: set[str] = set()


def read_dataset_json(folder, _depth: int = 0) -> dict:
    """``FOLDER/dataset.json`` read with its seal checked: the one reader of a dataset's index for ``make``, the head
    fits and ``histojax evaluate --dataset``. A file that carries a seal (:data:`DATASET_DIGEST`) must match it: an
    edit since histojax wrote it (a label, a split) is a ``BundleError`` naming the file. A split derived from a
    sealed dataset (``baselines.validation``: a ``validation.source`` record; the readers' ``derived_from``)
    carries its source's seal: the source's seal is checked and the labels must be the source's. Files without a
    seal (``data_tools synth``, older builds) are read as they are; one of a kind ``histojax dataset`` or ``c16``
    writes (:data:`SEALING_KINDS`) with a warning, once per file, that its labels are unchecked. ``FileNotFoundError``, ``OSError`` and
    ``json.JSONDecodeError`` pass as ``json.loads(path.read_text())`` raises them; a ``BundleError`` naming the
    file when it is not a regular file (a FIFO would block the read for ever; a folder, a device), larger than
    :data:`MAX_DATASET_JSON_BYTES`, or not a JSON object. Returns the object."""
    path = Path(folder) / "dataset.json"
    st = os.stat(path)  # a link to a regular file is read (the user's choice); FileNotFoundError as before
    if not stat.S_ISREG(st.st_mode):
        raise BundleError(path, f"is {not_regular(st)}, not a dataset index file; refusing to read it (rebuild the "
                          "dataset, or give the folder histojax wrote)")
    if st.st_size > MAX_DATASET_JSON_BYTES:
        raise BundleError(path, f"is {st.st_size / 2**20:.0f} MiB, more than a dataset index holds "
                          f"({MAX_DATASET_JSON_BYTES // 2**20} MiB); not a histojax dataset.json")
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # swapped for a FIFO since: never blocks
    with os.fdopen(fd, "rb") as f:
        if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
            raise BundleError(path, "changed while it was opened (not a regular file now); refusing to read it")
        data = f.read(MAX_DATASET_JSON_BYTES + 1)
    if len(data) > MAX_DATASET_JSON_BYTES:
        raise BundleError(path, f"grew past {MAX_DATASET_JSON_BYTES // 2**20} MiB while it was read; refusing it")
    spec = json.loads(data.decode("utf-8"))
    if not isinstance(spec, dict):
        raise BundleError(path, f"holds a JSON {type(spec).__name__}, not a dataset index (an object with the "
                          "train and test splits histojax writes); rebuild the dataset")
    if DATASET_DIGEST not in spec:
        if spec.get("kind") in SEALING_KINDS and str(path.resolve()) not in _UNSEALED_WARNED:
            _UNSEALED_WARNED.add(str(path.resolve()))
            warnings.warn(f"{path}: carries no seal ({DATASET_DIGEST}): written before histojax sealed its dataset "
                          "indexes, or the seal was removed; its labels and splits are read unchecked. Rebuild it "
                          "with the command that made it to seal it", stacklevel=2)
        return spec
    validation = spec.get("validation")
    source = spec.get("derived_from") or (validation.get("source") if isinstance(validation, dict) else None)
    if isinstance(source, str) and _depth < 4:
        try:
            base = read_dataset_json(source, _depth + 1)
        except FileNotFoundError:
            return spec  # the source moved away: its bundles' own checks report it
        if isinstance(base, dict) and isinstance(base.get("labels"), dict) and isinstance(spec.get("labels"), dict):
            theirs = {Path(str(k)).name: v for k, v in base["labels"].items()}
            changed = [k for k, v in spec["labels"].items() if theirs.get(Path(str(k)).name, v) != v]
            if changed:
                raise BundleError(path, f"labels differ from those of the sealed dataset it was split from ({source}; "
                                  f"e.g. {changed[0]!r}): edited since; split it again from {source}")
        return spec
    if spec[DATASET_DIGEST] != metadata_digest({k: v for k, v in spec.items() if k != DATASET_DIGEST}):
        raise BundleError(path, f"does not match its seal ({DATASET_DIGEST}): edited after histojax wrote it (a label, "
                          "a split or a slide record); restore it or rebuild it with the command that made it "
                          "(`histojax dataset SLIDES --out DIR`, `python -m data_tools c16 ... --out DIR`)")
    return spec


def write_metadata(folder, metadata: dict) -> None:
    """Write ``metadata.json`` of the bundle at ``folder`` atomically, sealed with its own digest
    (:data:`METADATA_DIGEST`), so an edit of any field is caught on a verified load."""
    metadata = {k: v for k, v in metadata.items() if k != METADATA_DIGEST}
    write_json(Path(folder) / METADATA, {**metadata, METADATA_DIGEST: metadata_digest(metadata)})


def verify_metadata(path, metadata: dict) -> None:
    """Check the digest of the bundle at ``path``'s metadata (``BundleError`` on a mismatch). Bundles
    written before metadata was sealed have no digest: a warning says so (their fields are still
    cross-checked against the arrays on load)."""
    recorded = metadata.get(METADATA_DIGEST)
    if recorded is None:
        import warnings

        warnings.warn(f"{path}: metadata.json is not sealed (bundle built before histojax sealed metadata); "
                      "only its cross-checks against the arrays are verified, rebuild the bundle to verify "
                      "every field", stacklevel=3)
    elif recorded != metadata_digest(metadata):
        raise BundleError(Path(path) / METADATA, f"metadata digest mismatch ({METADATA_DIGEST}): metadata.json "
                          "was edited after the build; rebuild the bundle")


BUNDLE_EXTRAS = ("features.partial",)
"""Entries a bundle may hold besides ``metadata.json`` and the files its checksums list: the chunks of an
unfinished feature grid (:mod:`data_tools.features`)."""


LEFT_RUN_LOCK = ".histojax-run.lock"
"""The lock file ``histojax train`` took in a folder it then refused (histojax 0.1.0 left it behind; now removed on
refusal): :func:`left_run_lock` tells such a leftover, which never makes a bundle or a head folder foreign."""


def left_run_lock(path) -> bool:
    """Whether ``path`` is a leftover run lock (:data:`LEFT_RUN_LOCK`): a small regular file (no link, no FIFO)
    holding only a process id, that no process holds (an ``fcntl.flock`` on it is free)."""
    import fcntl

    path = Path(path)
    try:
        st = os.lstat(path)
        if path.name != LEFT_RUN_LOCK or not stat.S_ISREG(st.st_mode) or st.st_size > 64:
            return False
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return False
    try:
        if not re.fullmatch(rb"\d*\s*", os.read(fd, 65)):
            return False
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held by a run: not a leftover
        fcntl.flock(fd, fcntl.LOCK_UN)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def foreign_entries(out_dir) -> list[str]:
    """The entries of the folder ``out_dir`` that histojax cannot prove it wrote as a bundle: everything when
    ``metadata.json`` is absent, not a regular file, or not a bundle's metadata (a JSON object with a known
    ``format_version`` and a ``checksums`` record); else every entry that is neither ``metadata.json``, a file
    its checksums list, :data:`BUNDLE_EXTRAS` nor a hidden ``.NAME.tmp-*`` of an interrupted atomic write.
    Empty when the folder is a bundle as histojax wrote it (or is empty)."""
    out_dir = Path(out_dir)
    entries = sorted(p.name for p in out_dir.iterdir() if not (p.name == TEMP_MARKER and p.is_file()
                                                                and not p.is_symlink()))
    meta = out_dir / METADATA
    try:
        if meta.is_symlink() or not meta.is_file():
            return entries
        metadata = json.loads(meta.read_text())
    except (OSError, ValueError):
        return entries
    if not isinstance(metadata, dict) or metadata.get("format_version") not in READ_VERSIONS \
            or not isinstance(metadata.get("checksums"), dict):
        return entries
    known = {METADATA, *BUNDLE_EXTRAS, *(k for k in metadata["checksums"] if isinstance(k, str))}
    foreign = []
    for name in entries:
        p = out_dir / name
        if name.startswith(".") and ".tmp-" in name and is_our_temporary(p):
            continue
        if name == LEFT_RUN_LOCK and left_run_lock(p):  # a refused `train --out` of histojax 0.1.0 left it
            continue
        if name not in known or p.is_symlink() or (name != PARTIAL and not p.is_file()):
            foreign.append(name)
        elif name == PARTIAL:
            foreign += [f"{PARTIAL}/{n}" for n in partial_foreign(p)]
    return foreign


PARTIAL = "features.partial"
"""The folder of an unfinished feature grid inside a bundle: ``settings.json`` and ``NNNNNN.npy`` chunks."""
PARTIAL_ENTRY = re.compile(r"^(?:settings\.json|[0-9]{6}\.npy)$")


def partial_foreign(partial) -> list[str]:
    """The entries of ``BUNDLE/features.partial`` histojax did not write (anything but ``settings.json``, regular
    ``NNNNNN.npy`` chunk files and marked temporaries); everything when it is not a real folder."""
    partial = Path(partial)
    if partial.is_symlink() or not partial.is_dir():
        return [partial.name]
    foreign = []
    for p in sorted(partial.iterdir()):
        if PARTIAL_ENTRY.match(p.name) and not p.is_symlink() and p.is_file():
            continue
        if p.name.startswith(".") and ".tmp-" in p.name and is_our_temporary(p):
            continue
        foreign.append(p.name)
    return foreign


def remove_partial(partial) -> bool:
    """Delete what histojax wrote in ``BUNDLE/features.partial`` (its chunks, settings and marked temporaries),
    then the folder if that left it empty; anything else (a user's file) stays. Returns whether it is gone."""
    partial = Path(partial)
    if partial.is_symlink() or not partial.is_dir():
        return False
    foreign = set(partial_foreign(partial))
    for p in partial.iterdir():
        if p.name in foreign:
            continue
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    try:
        partial.rmdir()
    except OSError:
        return False
    return True


def check_replaceable(out_dir) -> None:
    """Refuse to overwrite ``out_dir`` unless it is absent, an empty folder, or a bundle histojax wrote: its
    ``metadata.json`` a bundle's metadata and every other entry a file that metadata lists (see
    :func:`foreign_entries`). ``--overwrite`` must never delete files histojax did not write; a dataset folder
    (``dataset.json``) is never replaced by a bundle."""
    out_dir = Path(out_dir)
    if not (out_dir.exists() or out_dir.is_symlink()):
        return
    if out_dir.is_symlink() or not out_dir.is_dir():
        raise BundleError(out_dir, "is a file, not a bundle folder; refusing to overwrite it (remove it yourself "
                          "or choose another --out)")
    if not any(p.name != TEMP_MARKER for p in out_dir.iterdir()):
        return
    if (out_dir / "dataset.json").exists() or (out_dir / "dataset.json").is_symlink():
        raise BundleError(out_dir, "holds a dataset.json (a dataset folder, not a bundle); refusing to overwrite "
                          "it (choose another --out)")
    foreign = foreign_entries(out_dir)
    if foreign:
        what = (f"no readable {METADATA}" if METADATA in foreign or not (out_dir / METADATA).is_file()
                else f"{len(foreign)} file(s) its {METADATA} does not list, e.g. {foreign[0]!r}")
        raise BundleError(out_dir, f"is a folder of other files, not a histojax bundle ({what}); refusing to "
                          "overwrite it (remove them yourself or choose another --out)")


RENAME_EXCHANGE = 2  # renameat2 flag (Linux >= 3.15): swap two paths atomically


def _exchange(a: Path, b: Path) -> bool:
    """Swap the folders ``a`` and ``b`` in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``); False when
    the system cannot (another OS, an old kernel or libc, a filesystem without it): nothing changed then."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd = -100
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), RENAME_EXCHANGE) == 0


def replace_folder(new, out_dir) -> None:
    """Put the finished folder ``new`` (a sibling of ``out_dir``) at ``out_dir``: swapped in one atomic step
    where the system can (a reader sees the old folder or the new one, never none), else the old folder is
    renamed aside to ``.NAME.old-XXXXXXXX`` first and put back if the second rename fails. The old folder is
    marked a temporary (:func:`mark_temporary`) before it moves, so a run killed meanwhile leaves a folder the
    next run can prove is histojax's, and deleted once the new one is in place; the new ``out_dir`` keeps no
    marker (unless ``out_dir`` is itself a temporary, ``.NAME.tmp-*``). ``out_dir`` must be absent or a folder
    (not a link)."""
    new, out_dir = Path(new), Path(out_dir)

    def unmark() -> None:
        if not TEMP_NAME.match(out_dir.name):
            (out_dir / TEMP_MARKER).unlink(missing_ok=True)

    if not (out_dir.exists() or out_dir.is_symlink()):
        new.rename(out_dir)
        unmark()
        return
    if out_dir.is_symlink() or not out_dir.is_dir():
        raise BundleError(out_dir, "is a file, not a bundle folder; refusing to replace it")
    mark_temporary(out_dir)
    if _exchange(new, out_dir):
        unmark()
        shutil.rmtree(new, ignore_errors=True)  # now the old folder
        return
    old = out_dir.parent / f".{out_dir.name}.old-{uuid.uuid4().hex[:8]}"
    out_dir.rename(old)
    try:
        new.rename(out_dir)
    except BaseException:
        old.rename(out_dir)  # put the previous folder back
        unmark()
        raise
    unmark()
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_folder(out_dir):
    """Yield a temporary sibling folder of ``out_dir`` (``.NAME.tmp-XXXXXXXX``, created and marked as histojax's,
    :func:`mark_temporary`) to fill; when the block ends it replaces ``out_dir`` (:func:`replace_folder`: an atomic
    swap where the system can, else the previous ``out_dir`` is moved aside first and put back if the rename
    fails), so a crash leaves nothing that looks like a bundle. On an error the temporary folder is removed and
    ``out_dir`` is left as it was."""
    out_dir = Path(out_dir)
    tmp = out_dir.parent / f".{out_dir.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        mark_temporary(tmp)
        yield tmp
        replace_folder(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


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
        raise BundleError(folder, f"has no feature grid; compute one first (`{FEATURES_COMMAND}`), a bundle "
                          "without pixels and features is of no use")
    levels, files = [], []
    for k, lv in enumerate(metadata["levels"]):
        lv = dict(lv)
        if k < len(metadata["levels"]) - 1 and lv.get("tiles"):
            files.append(lv["tiles"])
            lv["tiles"] = None
        levels.append(lv)
    checksums = {k: v for k, v in metadata.checksums.items() if k not in files}
    write_metadata(folder, {**metadata, "levels": levels, "checksums": checksums,
                            "pixels_dropped": "RGB tile pools of every level but the coarsest deleted "
                                              "(feature-only bundle); device_bytes is the pixel layout's"})
    freed = 0
    for name in files:
        f = folder / name
        if f.is_file():
            freed += f.stat().st_size
            f.unlink()
    return freed


# ----------------------------------------------------------------------------- verified read
@dataclass
class TiledLevel:
    """A tiled level on the host: ``pool[index[ty, tx]]`` is tile ``(ty, tx)``. Behaves like the dense
    ``(H, W, 3)`` (or, for tumour, ``(H, W)``) array for ``shape``, 2-D slicing and ``np.asarray``
    (materialised on demand: only for small levels or crops)."""

    pool: np.ndarray   # (N, T, T, 3) uint8 or (M, T+1, T+1) uint32 local SATs
    index: np.ndarray  # (gh, gw) int32
    height: int
    width: int
    kind: str = "pixels"  # "pixels" or "tumour" (SAT pool → 0/1 mask)

    @property
    def has_pixels(self) -> bool:
        """False for a pixel level whose tile pool was dropped (:func:`drop_pixels`): shape and index only."""
        return self.kind != "pixels" or self.pool.shape[0] > 0

    @property
    def tile_size(self) -> int:
        return int(self.pool.shape[1]) - (1 if self.kind == "tumour" else 0)

    @property
    def shape(self):
        return (self.height, self.width, 3) if self.kind == "pixels" else (self.height, self.width)

    @property
    def dtype(self):
        return np.dtype(np.uint8)

    @property
    def ndim(self) -> int:
        return len(self.shape)

    def _tiles(self, ids: np.ndarray) -> np.ndarray:
        tiles = np.asarray(self.pool[ids.ravel()])
        if self.kind == "tumour":
            s = tiles.astype(np.int64)
            tiles = (s[:, 1:, 1:] - s[:, :-1, 1:] - s[:, 1:, :-1] + s[:, :-1, :-1]).astype(np.uint8)
        return tiles

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> np.ndarray:
        """Rows ``y0:y1`` and columns ``x0:x1`` (px, clipped to the level) as a dense array."""
        y0, y1, x0, x1 = max(0, y0), min(self.height, y1), max(0, x0), min(self.width, x1)
        t = self.tile_size
        if y1 <= y0 or x1 <= x0:
            return np.zeros((max(0, y1 - y0), max(0, x1 - x0)) + self.shape[2:], np.uint8)
        ty0, ty1, tx0, tx1 = y0 // t, (y1 - 1) // t + 1, x0 // t, (x1 - 1) // t + 1
        ids = self.index[ty0:ty1, tx0:tx1]
        tiles = self._tiles(ids).reshape(ids.shape + (t, t) + self.shape[2:])
        full = np.moveaxis(tiles, 2, 1).reshape((ids.shape[0] * t, ids.shape[1] * t) + self.shape[2:])
        return np.ascontiguousarray(full[y0 - ty0 * t:y1 - ty0 * t, x0 - tx0 * t:x1 - tx0 * t])

    def __getitem__(self, key):
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (2 - len(key))
        rows, cols = key[0], key[1]
        if not (isinstance(rows, slice) and isinstance(cols, slice)) or rows.step not in (None, 1) \
                or cols.step not in (None, 1):
            return np.asarray(self)[key]
        y0, y1, _ = rows.indices(self.height)
        x0, x1, _ = cols.indices(self.width)
        out = self.crop(y0, y1, x0, x1)
        return out[(slice(None), slice(None)) + key[2:]] if len(key) > 2 else out

    def __array__(self, dtype=None, copy=None):
        out = self.crop(0, self.height, 0, self.width)
        return out if dtype is None else out.astype(dtype)

    def sum(self) -> int:
        """Sum of the level (tumour px count for a tumour level) without materialising it."""
        if self.kind != "tumour":
            return int(np.asarray(self).sum())
        t = self.tile_size
        totals = np.asarray(self.pool[:, t, t]).astype(np.int64)
        return int(totals[self.index].sum())


@dataclass(frozen=True)
class Bundle:
    """A loaded bundle (host numpy arrays). ``levels`` are finest first, as in the metadata."""

    path: Path
    metadata: BundleMetadata
    pixels: list[np.ndarray]   # (H, W, 3) uint8 per level (tiled bundles: lazy TiledLevel)
    tumour: list[np.ndarray]   # (H, W) uint8 0/1 per level (tiled bundles: TiledLevel of local SATs)
    tissue: np.ndarray         # (H, W) bool at the coarsest bundle level
    region: np.ndarray | None = None  # (H, W) bool at the coarsest level: allowed view centres (region bundles)

    @property
    def downsamples(self) -> list[float]:
        return [lv["downsample"] for lv in self.metadata["levels"]]

    @property
    def tile_size(self) -> int:
        return int(self.metadata["tile_size"])

    @property
    def storage(self) -> str:
        return self.metadata.get("storage", "dense")


def read_metadata(path) -> BundleMetadata:
    """Read and check ``metadata.json`` of the bundle at ``path`` (format version, fields)."""
    path = Path(path)
    meta_file = path / METADATA
    if not meta_file.is_file() and not meta_file.is_symlink():
        raise BundleError(path, f"not a slide bundle (no {METADATA}); build one with "
                          "`python -m data_tools build SLIDE --out DIR`")
    own_file(path, METADATA, "metadata")
    try:
        metadata = json.loads(meta_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BundleError(meta_file, f"unreadable metadata ({e}); rebuild the bundle") from None
    if not isinstance(metadata, dict):
        raise BundleError(meta_file, "metadata is not a JSON object; rebuild the bundle")
    if metadata.get("format_version") not in READ_VERSIONS:
        raise BundleError(path, f"bundle format version {metadata.get('format_version')!r}, this histojax reads "
                          f"versions {READ_VERSIONS}; rebuild it with `python -m data_tools build`")
    if (metadata.get("storage", "dense") == "tiled") != (metadata["format_version"] == TILED_FORMAT_VERSION):
        raise BundleError(meta_file, "storage and format version disagree; rebuild the bundle")
    for key in ("tile_size", "levels", "checksums", "magnification_range", "tissue"):
        if key not in metadata:
            raise BundleError(meta_file, f"metadata lacks {key!r}; rebuild the bundle")
    check_fields(meta_file, metadata)
    return BundleMetadata(metadata)


MIN_TILE_SIZE = 8  # px; the smallest view a build accepts


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def safe_name(name, where) -> str:
    """``name`` if it is a plain file name inside the bundle folder (no folder part, not ``.``/``..``),
    else ``BundleError``: metadata may only point at the bundle's own files."""
    if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name \
            or "\0" in name or Path(name).name != name:
        raise BundleError(where, f"file entry {name!r} is not a file name inside the bundle; rebuild the bundle")
    return name


def check_fields(where, metadata: dict) -> None:
    """Check the types and ranges of the fields readers use (tile size, levels, file names, tissue), so a
    malformed ``metadata.json`` is refused naming it instead of failing later inside numpy."""
    def bad(problem):
        raise BundleError(where, f"{problem}; rebuild the bundle")

    t = metadata["tile_size"]
    if not _is_int(t) or t < MIN_TILE_SIZE:
        bad(f"tile_size {t!r} must be a whole number of px >= {MIN_TILE_SIZE}")
    r = metadata["magnification_range"]
    if not _is_number(r) or r < 1:
        bad(f"magnification_range {r!r} must be a finite number >= 1")
    levels = metadata["levels"]
    if not isinstance(levels, list) or not levels or not all(isinstance(lv, dict) for lv in levels):
        bad("levels must be a non-empty list of level records")
    tiled = metadata.get("storage", "dense") == "tiled"
    names = ("tiles", "tile_index", "sat_tiles", "sat_index") if tiled else ("pixels", "tumour")
    for k, lv in enumerate(levels):
        for key in ("width", "height"):
            if not _is_int(lv.get(key)) or not 1 <= lv[key] < 2**31:
                bad(f"level {k} {key} {lv.get(key)!r} must be a whole number of px in [1, 2**31)")
        d = lv.get("downsample")
        if not _is_number(d) or d < 1 - 1e-9:
            bad(f"level {k} downsample {d!r} must be a finite number >= 1")
        for key in names:
            if key == "tiles" and lv.get(key) is None:
                continue  # pixels dropped (drop_pixels)
            safe_name(lv.get(key), where)
        if not tiled and not (lv["width"] >= t and lv["height"] >= t):
            bad(f"level {k} ({lv['width']}×{lv['height']} px) is smaller than one {t}-px view")
    downsamples = [lv["downsample"] for lv in levels]
    if any(b <= a for a, b in zip(downsamples, downsamples[1:])):
        bad(f"level downsamples {downsamples} must increase (finest first)")
    tissue = metadata["tissue"]
    if not isinstance(tissue, dict):
        bad("tissue must be a record with the mask's file")
    safe_name(tissue.get("file"), where)
    if "level" in tissue and tissue["level"] != len(levels) - 1:
        bad(f"tissue level {tissue['level']!r} is not the coarsest level {len(levels) - 1}")
    region = metadata.get("region")
    if region is not None and (not isinstance(region, dict) or (region.get("mask") is not None
                                                                  and not safe_name(region["mask"], where))):
        bad("region must be a record")
    if not isinstance(metadata["checksums"], dict):
        bad("checksums must be a record of file name -> SHA-256")


def load_array(path, name: str, metadata: dict, verify: bool, mmap: bool = False) -> np.ndarray:
    """The array ``name`` of the bundle at ``path`` (no pickles), its SHA-256 checked against the
    metadata when ``verify``; ``mmap`` memory-maps it read-only."""
    path = Path(path)
    file = own_file(path, name, "array")
    try:
        fd = os.open(file, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))  # a link put there since: refused (ELOOP)
    except OSError as e:
        raise BundleError(path, f"entry {name!r} cannot be opened as the bundle's own file ({e.strerror or e}); "
                          "rebuild the bundle") from None
    with os.fdopen(fd, "rb") as f:
        if verify:
            h = hashlib.sha256()
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
            if h.hexdigest() != metadata["checksums"].get(name):
                raise BundleError(file, "checksum mismatch (the file changed or is corrupt); rebuild the bundle")
            f.seek(0)
        try:
            if mmap:
                own_file(path, name, "array")  # still the file just checked (memmap opens by name)
                return np.load(file, allow_pickle=False, mmap_mode="r")
            return np.load(f, allow_pickle=False)
        except Exception as e:  # a corrupt header raises ValueError, SyntaxError, tokenize.TokenError, ...
            problem = " ".join(str(e).split())[:200] or type(e).__name__
            raise BundleError(file, f"unreadable array ({problem}); rebuild the bundle") from None


def bundle_damage(path) -> str | None:
    """None when the bundle at ``path`` is whole: its ``metadata.json`` reads and its seal matches, and every
    file its checksums list is the bundle's own regular file (:func:`own_file`) with the recorded SHA-256 (every
    byte of every file is read: seconds per GB). Else one line naming the file and what is wrong. Used by dataset
    reruns to decide that a finished slide's bundle must be built again."""
    import warnings

    path = Path(path)
    try:
        metadata = read_metadata(path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # a bundle sealed before metadata.json was: its files still checked
            verify_metadata(path, metadata)
        for name, digest in metadata["checksums"].items():
            file = own_file(path, name, "file")
            fd = os.open(file, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
            h = hashlib.sha256()
            with os.fdopen(fd, "rb") as f:
                for chunk in iter(lambda: f.read(1 << 20), b""):
                    h.update(chunk)
            if h.hexdigest() != digest:
                return f"{file}: checksum mismatch (the file changed or is corrupt)"
    except BundleError as e:
        return str(e)
    except OSError as e:
        return f"{e.filename or path}: {e.strerror or e}"
    return None


def not_regular(st: os.stat_result) -> str | None:
    """None when ``st`` (an ``os.lstat`` result) is a regular file; else what the entry is instead (``"a symbolic
    link"``, ``"a FIFO"``, ``"a folder"``, ``"a device"``, ``"a socket"``): the one regular-file guard every reader
    of a user's files shares (bundles here, slide heads in :mod:`histojax.reading.heads.files`). A FIFO would block
    ``open``; a link may point anywhere."""
    import stat

    mode = st.st_mode
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISLNK(mode):
        return "a symbolic link"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "a socket" if stat.S_ISSOCK(mode) else "not a regular file"


class ChangedFileError(OSError):
    """The file opened is not the regular file :func:`not_regular` checked (swapped in between)."""


def open_regular(path, st: os.stat_result):
    """``path`` opened for binary reading (a file object), after :func:`not_regular` passed on its ``lstat``
    result ``st``: opened with ``O_NOFOLLOW | O_NONBLOCK`` (a link put there since fails with ``ELOOP``; a FIFO
    never blocks) and ``fstat``-ed again. ``ChangedFileError`` when what was opened is not a regular file or not
    the same file as ``st`` (device, inode); ``OSError`` when it cannot be opened."""
    import stat

    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    f = os.fdopen(fd, "rb")
    now = os.fstat(f.fileno())
    if not stat.S_ISREG(now.st_mode) or (now.st_dev, now.st_ino) != (st.st_dev, st.st_ino):
        f.close()
        raise ChangedFileError(f"{path}: not the regular file checked (it changed while it was opened)")
    return f


def own_file(bundle, name: str, what: str = "file") -> Path:
    """``BUNDLE/NAME`` after checking that the entry is the bundle's own regular file: a plain name
    (:func:`safe_name`), present, not a symbolic link, a FIFO, a device or a folder (``os.lstat``,
    :func:`not_regular`), whose resolved path lies in the bundle folder. Else a ``BundleError`` naming the bundle
    and the entry: a bundle never reads a file outside itself (``ln -s /etc/passwd BUNDLE/tissue.npy`` is
    refused)."""
    bundle = Path(bundle)
    file = bundle / safe_name(name, bundle / METADATA)
    try:
        st = os.lstat(file)
    except FileNotFoundError:
        raise BundleError(bundle, f"missing {what} {name}; rebuild the bundle") from None
    except OSError as e:
        raise BundleError(bundle, f"entry {name!r} cannot be read ({e.strerror or e}); rebuild the bundle") from None
    kind = not_regular(st)
    if kind == "a symbolic link":
        try:
            target = os.readlink(file)
        except OSError:
            target = "?"
        raise BundleError(bundle, f"entry {name!r} is a symbolic link (to {target}), not the bundle's own file; "
                          "refusing to read it (rebuild the bundle)")
    if kind is not None:
        raise BundleError(bundle, f"entry {name!r} is not a regular file; refusing to read it (rebuild the bundle)")
    if os.path.realpath(file.parent) != os.path.realpath(bundle):
        raise BundleError(bundle, f"entry {name!r} resolves outside the bundle; refusing to read it")
    return file


def check_mask(file, array, shape, kind: str = "0/1") -> None:
    """Refuse a mask whose shape is not ``shape`` or whose values are not 0/1 (``kind`` names what it holds):
    another program's 0/255 mask would count every tumour pixel 255 times."""
    if array.shape != tuple(shape):
        raise BundleError(file, f"{kind} mask of shape {array.shape}, expected {tuple(shape)} from the metadata; "
                          "rebuild the bundle")
    if array.dtype == np.bool_:
        return
    if array.dtype.kind not in "ui":
        raise BundleError(file, f"{kind} mask of dtype {array.dtype}, expected bool or uint8 0/1; rebuild the bundle")
    top = int(np.max(array)) if array.size else 0
    low = int(np.min(array)) if array.size else 0
    if top > 1 or low < 0:
        raise BundleError(file, f"{kind} mask holds values in [{low}, {top}], expected 0/1 (a 0/255 mask from "
                          "another program?); rebuild the bundle")


def load_tiled_level(path, lv: dict, metadata: dict, verify: bool, kind: str) -> TiledLevel:
    """One tiled level as a lazy :class:`TiledLevel` (pools memory-mapped); ``kind`` is
    ``"pixels"`` or ``"tumour"``."""
    path = Path(path)
    t = int(metadata["tile_size"])
    pool_name, index_name = ("tiles", "tile_index") if kind == "pixels" else ("sat_tiles", "sat_index")
    item = (t, t, 3) if kind == "pixels" else (t + 1, t + 1)
    dtype = np.uint8 if kind == "pixels" else np.uint32
    dropped = kind == "pixels" and lv.get(pool_name) is None  # pixels dropped (see drop_pixels)
    pool = np.zeros((0, *item), dtype) if dropped else load_array(path, lv[pool_name], metadata, verify, mmap=True)
    index = load_array(path, lv[index_name], metadata, verify)
    grid = (-(-lv["height"] // t), -(-lv["width"] // t))
    if pool.shape[1:] != item or pool.dtype != dtype or index.shape != grid or index.dtype != np.int32 \
            or (not dropped and (pool.shape[0] < 1 or (index.size and (index.min() < 0
                                                                       or index.max() >= pool.shape[0])))):
        raise BundleError(path / (lv[pool_name] or lv[index_name]),
                          "tile pool or index disagrees with metadata; rebuild the bundle")
    if kind == "tumour" and pool.shape[0] and int(np.max(pool[:, t, t])) > t * t:
        raise BundleError(path / lv[pool_name], f"a tumour tile counts more than {t * t} px (its mask is not 0/1); "
                          "rebuild the bundle")
    return TiledLevel(pool=pool, index=index, height=int(lv["height"]), width=int(lv["width"]), kind=kind)


def load_bundle(path, verify: bool = True, levels: list[int] | None = None, mmap: bool = False,
                metadata: dict | None = None) -> Bundle:
    """Load the bundle at ``path`` (host numpy arrays); ``levels`` selects bundle level indices
    (finest first, as in the metadata; default all). Checksums are verified unless ``verify=False``.
    ``mmap=True`` memory-maps the dense level arrays (read-only) instead of reading them into memory.
    ``metadata`` skips reading ``metadata.json`` again when the caller has just read (and, with ``verify``,
    checked with :func:`verify_metadata`) it; without it the metadata's digest is checked (``verify``) and a
    folder swapped by a concurrent rebuild is read again (:func:`stable_read`)."""
    if metadata is None:  # a bundle swapped by a rebuild while we read is read again, whole
        def read():
            meta = read_metadata(path)
            if verify:
                verify_metadata(path, meta)
            return load_bundle(path, verify, levels, mmap, meta)

        return stable_read(path, read)
    path = Path(path)
    metadata = BundleMetadata(metadata)
    chosen = range(len(metadata["levels"])) if levels is None else levels
    pixels, tumour = [], []
    for k in chosen:
        lv = metadata["levels"][k]
        if lv.get("storage") == "tiled":
            pixels.append(load_tiled_level(path, lv, metadata, verify, "pixels"))
            tumour.append(load_tiled_level(path, lv, metadata, verify, "tumour"))
            continue
        pixels.append(load_array(path, lv["pixels"], metadata, verify, mmap=mmap))
        tumour.append(load_array(path, lv["tumour"], metadata, verify, mmap=mmap))
        for name, array, shape in ((lv["pixels"], pixels[-1], (lv["height"], lv["width"], 3)),
                                   (lv["tumour"], tumour[-1], (lv["height"], lv["width"]))):
            if array.shape != shape or array.dtype != np.uint8:
                raise BundleError(path / name, f"array {array.shape} {array.dtype} disagrees with the metadata "
                                  f"({shape} uint8); rebuild the bundle")
        check_mask(path / lv["tumour"], tumour[-1], (lv["height"], lv["width"]), "tumour")
        recorded = lv.get("tumour_pixels")
        if recorded is not None and recorded != int(np.sum(tumour[-1], dtype=np.int64)):
            raise BundleError(path / METADATA, f"level {k} records {recorded!r} tumour px, {lv['tumour']} holds "
                              f"{int(np.sum(tumour[-1], dtype=np.int64))}; rebuild the bundle")
    coarsest = metadata["levels"][-1]
    tissue = load_array(path, metadata.tissue_file, metadata, verify)
    check_mask(path / metadata.tissue_file, tissue, (coarsest["height"], coarsest["width"]), "tissue")
    region = None
    if metadata.region_mask_file:
        region = load_array(path, metadata.region_mask_file, metadata, verify)
        check_mask(path / metadata.region_mask_file, region, (coarsest["height"], coarsest["width"]), "region")
        region = region.astype(bool)
    return Bundle(path=path, metadata=metadata, pixels=pixels, tumour=tumour, tissue=tissue, region=region)


def _identity(path):
    """``(device, inode, ctime)`` of the folder at ``path`` (a rename sets its ctime), ``None`` when there is none."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_ctime_ns


def _rebuilding(path: Path) -> bool:
    """True while a build of ``path`` is under way: its temporary folder, moved-aside old folder or build lock
    lies beside it (see :func:`atomic_folder` and :func:`data_tools.bundle.build_lock`)."""
    import glob as _glob

    stem = str(path.parent / f".{_glob.escape(path.name)}.")
    return bool(_glob.glob(stem + "tmp-*") or _glob.glob(stem + "old-*") or os.path.exists(stem + "lock"))


def stable_read(path, read, attempts: int = 12):
    """``read()`` of the bundle at ``path``, repeated when the folder was swapped while it ran (a rebuild with
    ``--overwrite`` renames a new folder into place, see :func:`atomic_folder`): a verified read is all of the
    old bundle or all of the new one, never a mix, and a swap is never reported as corruption. A read is
    repeated when the folder's identity (inode, ctime) changed, or when it failed while a rebuild was under
    way (a ``BundleError``, or an ``OSError`` such as a file that vanished mid-swap); an error with no rebuild in
    sight is raised at once, and after ``attempts`` tries (10 s of waits in all,
    doubling from 5 ms: a reader outlasts a busy machine's run of back-to-back rebuilds)."""
    import time

    path = Path(path)
    for attempt in range(attempts):
        last = attempt == attempts - 1
        before = _identity(path)
        try:
            result = read()
        except (BundleError, OSError):  # OSError: a file vanished between the rename aside and the new folder's
            if last or (_identity(path) == before and not _rebuilding(path)):
                raise
            time.sleep(0.005 * 2 ** attempt)
            continue
        if last or _identity(path) == before:
            return result
        time.sleep(0.005 * 2 ** attempt)
    raise AssertionError("unreachable")


def load_feature_levels(bundle, metadata: dict, levels: list[int], verify: bool = True):
    """The feature grids of bundle ``levels`` (indices into ``metadata["levels"]``) and the grid
    stride: ``([(gh, gw, D) arrays], stride)``. Raises ``BundleError`` naming the command to run
    when the bundle has no feature grid."""
    bundle = Path(bundle)
    info = metadata.get("features")
    if not info:
        raise BundleError(bundle, "has no feature grid (needed for obs_mode='features'); compute one with "
                          f"`python -m data_tools features {bundle}` or import one with "
                          f"`python -m data_tools import-features {bundle} FILE.h5 --patch-size P --level L`")
    stride, dim = int(info["stride"]), int(info["dim"])
    expected = level_grids(metadata, stride)
    arrays = []
    for k in levels:
        entry = info["levels"][k]
        array = load_array(bundle, entry["file"], metadata, verify)
        if array.shape != (*expected[k], dim) or array.dtype.kind != "f":
            raise BundleError(bundle / entry["file"], f"feature grid of shape {array.shape} ({array.dtype}), expected "
                              f"{(*expected[k], dim)} floats; recompute it with `{FEATURES_COMMAND}`")
        arrays.append(array)
    return arrays, stride


__all__ = ["ANNOTATIONS", "Bundle", "BundleMetadata", "FEATURES_COMMAND", "FORMAT_VERSION", "LEVEL_SETS",
           "LevelMeta", "MAX_FLAT_PIXELS", "METADATA", "READ_VERSIONS", "REGION", "STORAGES", "TILED_FORMAT_VERSION",
           "TISSUE", "TiledLevel", "atomic_file", "atomic_folder", "bundle_downsamples", "default_magnification_range",
           "device_bytes", "drop_pixels", "feature_bytes", "file_digest", "slide_device_bytes", "tumour_table_bytes", "select_levels", "grid_shape", "level_device_bytes", "level_downsamples", "level_files",
           "level_grids", "level_size", "load_array", "load_bundle", "load_feature_levels", "load_tiled_level",
           "read_metadata", "save_array", "sha256", "stable_read", "check_replaceable", "verify_metadata", "metadata_digest", "METADATA_DIGEST", "check_mask", "check_fields", "safe_name", "own_file", "foreign_entries", "replace_folder", "bundle_damage", "as_disk_full", "DATASET_DIGEST", "read_dataset_json", "TEMP_MARKER", "mark_temporary", "is_our_temporary", "remove_temporary", "PARTIAL", "partial_foreign", "remove_partial", "text_digest", "tiled_level_files", "write_json", "write_metadata"]
