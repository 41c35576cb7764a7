"""The verified read of every kind of bundle (dense, tiled, feature grids): ``metadata.json`` read and its fields
checked (:func:`read_metadata`, :func:`check_fields`), every array checked against its recorded SHA-256 and shape
(:func:`load_array`) and read with ``allow_pickle=False``, and the host-side :class:`Bundle` returned
(:func:`load_bundle`); :func:`read_slide` is the one verified read of a scenario's levels that
``histojax.loading`` packs onto the device; :func:`bundle_damage` says what is wrong with a bundle without raising.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from data_tools.bundle_files.format import (
    FEATURES_COMMAND,
    METADATA,
    READ_VERSIONS,
    TILED_FORMAT_VERSION,
    BundleMetadata,
    level_grids,
    select_levels,
)
from data_tools.bundle_files.safe_files import own_file, safe_name, stable_read
from data_tools.bundle_files.seals import verify_metadata
from data_tools.errors import BundleError

__all__ = [
    "Bundle",
    "MIN_TILE_SIZE",
    "TiledLevel",
    "bundle_damage",
    "check_fields",
    "check_mask",
    "load_array",
    "load_bundle",
    "load_feature_levels",
    "load_tiled_level",
    "read_metadata",
    "read_slide",
    "SlideRead",
    "check_levels",
]


@dataclass
class TiledLevel:
    """A tiled level on the host: ``pool[index[ty, tx]]`` is tile ``(ty, tx)``. Behaves like the dense
    ``(H, W, 3)`` (or, for tumour, ``(H, W)``) array for ``shape``, 2-D slicing and ``np.asarray``
    (materialised on demand: only for small levels or crops)."""

    pool: np.ndarray  # (N, T, T, 3) uint8 or (M, T+1, T+1) uint32 local SATs
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
        return np.ascontiguousarray(full[y0 - ty0 * t : y1 - ty0 * t, x0 - tx0 * t : x1 - tx0 * t])

    def __getitem__(self, key):
        if not isinstance(key, tuple):
            key = (key,)
        key = key + (slice(None),) * (2 - len(key))
        rows, cols = key[0], key[1]
        if (
            not (isinstance(rows, slice) and isinstance(cols, slice))
            or rows.step not in (None, 1)
            or cols.step not in (None, 1)
        ):
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
    pixels: list[np.ndarray]  # (H, W, 3) uint8 per level (tiled bundles: lazy TiledLevel)
    tumour: list[np.ndarray]  # (H, W) uint8 0/1 per level (tiled bundles: TiledLevel of local SATs)
    tissue: np.ndarray  # (H, W) bool at the coarsest bundle level
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
        raise BundleError(
            path, f"not a slide bundle (no {METADATA}); build one with `python -m data_tools build SLIDE --out DIR`"
        )
    own_file(path, METADATA, "metadata")
    try:
        metadata = json.loads(meta_file.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BundleError(meta_file, f"unreadable metadata ({e}); rebuild the bundle") from None
    if not isinstance(metadata, dict):
        raise BundleError(meta_file, "metadata is not a JSON object; rebuild the bundle")
    if metadata.get("format_version") not in READ_VERSIONS:
        raise BundleError(
            path,
            f"bundle format version {metadata.get('format_version')!r}, this histojax reads "
            f"versions {READ_VERSIONS}; rebuild it with `python -m data_tools build`",
        )
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
    if region is not None and (
        not isinstance(region, dict) or (region.get("mask") is not None and not safe_name(region["mask"], where))
    ):
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
        raise BundleError(
            path, f"entry {name!r} cannot be opened as the bundle's own file ({e.strerror or e}); rebuild the bundle"
        ) from None
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


def check_mask(file, array, shape, kind: str = "0/1") -> None:
    """Refuse a mask whose shape is not ``shape`` or whose values are not 0/1 (``kind`` names what it holds):
    another program's 0/255 mask would count every tumour pixel 255 times."""
    if array.shape != tuple(shape):
        raise BundleError(
            file, f"{kind} mask of shape {array.shape}, expected {tuple(shape)} from the metadata; rebuild the bundle"
        )
    if array.dtype == np.bool_:
        return
    if array.dtype.kind not in "ui":
        raise BundleError(file, f"{kind} mask of dtype {array.dtype}, expected bool or uint8 0/1; rebuild the bundle")
    top = int(np.max(array)) if array.size else 0
    low = int(np.min(array)) if array.size else 0
    if top > 1 or low < 0:
        raise BundleError(
            file,
            f"{kind} mask holds values in [{low}, {top}], expected 0/1 (a 0/255 mask from "
            "another program?); rebuild the bundle",
        )


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
    if (
        pool.shape[1:] != item
        or pool.dtype != dtype
        or index.shape != grid
        or index.dtype != np.int32
        or (not dropped and (pool.shape[0] < 1 or (index.size and (index.min() < 0 or index.max() >= pool.shape[0]))))
    ):
        raise BundleError(
            path / (lv[pool_name] or lv[index_name]), "tile pool or index disagrees with metadata; rebuild the bundle"
        )
    if kind == "tumour" and pool.shape[0] and int(np.max(pool[:, t, t])) > t * t:
        raise BundleError(
            path / lv[pool_name], f"a tumour tile counts more than {t * t} px (its mask is not 0/1); rebuild the bundle"
        )
    return TiledLevel(pool=pool, index=index, height=int(lv["height"]), width=int(lv["width"]), kind=kind)


def load_bundle(
    path, verify: bool = True, levels: list[int] | None = None, mmap: bool = False, metadata: dict | None = None
) -> Bundle:
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
        for name, array, shape in (
            (lv["pixels"], pixels[-1], (lv["height"], lv["width"], 3)),
            (lv["tumour"], tumour[-1], (lv["height"], lv["width"])),
        ):
            if array.shape != shape or array.dtype != np.uint8:
                raise BundleError(
                    path / name,
                    f"array {array.shape} {array.dtype} disagrees with the metadata "
                    f"({shape} uint8); rebuild the bundle",
                )
        check_mask(path / lv["tumour"], tumour[-1], (lv["height"], lv["width"]), "tumour")
        recorded = lv.get("tumour_pixels")
        if recorded is not None and recorded != int(np.sum(tumour[-1], dtype=np.int64)):
            raise BundleError(
                path / METADATA,
                f"level {k} records {recorded!r} tumour px, {lv['tumour']} holds "
                f"{int(np.sum(tumour[-1], dtype=np.int64))}; rebuild the bundle",
            )
    coarsest = metadata["levels"][-1]
    tissue = load_array(path, metadata.tissue_file, metadata, verify)
    check_mask(path / metadata.tissue_file, tissue, (coarsest["height"], coarsest["width"]), "tissue")
    region = None
    if metadata.region_mask_file:
        region = load_array(path, metadata.region_mask_file, metadata, verify)
        check_mask(path / metadata.region_mask_file, region, (coarsest["height"], coarsest["width"]), "region")
        region = region.astype(bool)
    return Bundle(path=path, metadata=metadata, pixels=pixels, tumour=tumour, tissue=tissue, region=region)


def load_feature_levels(bundle, metadata: dict, levels: list[int], verify: bool = True):
    """The feature grids of bundle ``levels`` (indices into ``metadata["levels"]``) and the grid
    stride: ``([(gh, gw, D) arrays], stride)``. Raises ``BundleError`` naming the command to run
    when the bundle has no feature grid."""
    bundle = Path(bundle)
    info = metadata.get("features")
    if not info:
        raise BundleError(
            bundle,
            "has no feature grid (needed for obs_mode='features'); compute one with "
            f"`python -m data_tools features {bundle}` or import one with "
            f"`python -m data_tools import-features {bundle} FILE.h5 --patch-size P --level L`",
        )
    stride, dim = int(info["stride"]), int(info["dim"])
    expected = level_grids(metadata, stride)
    arrays = []
    for k in levels:
        entry = info["levels"][k]
        array = load_array(bundle, entry["file"], metadata, verify)
        if array.shape != (*expected[k], dim) or array.dtype.kind != "f":
            raise BundleError(
                bundle / entry["file"],
                f"feature grid of shape {array.shape} ({array.dtype}), expected "
                f"{(*expected[k], dim)} floats; recompute it with `{FEATURES_COMMAND}`",
            )
        arrays.append(array)
    return arrays, stride


def check_levels(path, metadata, chosen: list[int]) -> None:
    """Refuse scenario levels (bundle indices, coarsest first) between which zooming does nothing: the same
    bundle level twice (a bundle built with magnification range 1) or two levels of the same size."""
    t = int(metadata["tile_size"])
    sizes = [
        (max(t, int(metadata["levels"][k]["width"])), max(t, int(metadata["levels"][k]["height"]))) for k in chosen
    ]
    for a, b, size0, size in zip(chosen, chosen[1:], sizes, sizes[1:]):
        if a == b or size0 == size:
            raise BundleError(
                path,
                f"{len(chosen)} zoom levels would show bundle levels of the same size "
                f"({size[0]}×{size[1]} px, magnification range {metadata['magnification_range']:g}, "
                f"tile {t} px): zooming would do nothing; rebuild it with a larger "
                "--magnification-range or a smaller --tile-size",
            )


def _pixels_hint(path: Path) -> str:
    """How the feature-only bundle at ``path`` was made and how to make it again with its pixels: from the
    ``kind`` of the ``dataset.json`` of the dataset holding it (``histojax dataset`` or ``data_tools c16``)."""
    try:
        kind = str(json.loads((path.parent.parent / "dataset.json").read_text()).get("kind", ""))
    except (OSError, ValueError, AttributeError):
        kind = ""
    if "data_tools dataset" in kind:
        return (
            "with `histojax dataset ... --no-pixels`): use obs_mode='features', or build the dataset again with "
            f"its pixels (the same `histojax dataset SLIDES --out {path.parent.parent}` command and options, "
            "without --no-pixels)"
        )
    if "data_tools c16" in kind:
        return (
            "with `python -m data_tools c16 --no-pixels`): use obs_mode='features', or make these slides "
            "again with their pixels (the same `data_tools c16` command without --no-pixels, "
            f"--slides {path.name})"
        )
    return (
        "with --no-pixels): use obs_mode='features', or build the bundle again with its pixels (the same "
        "command without --no-pixels)"
    )


@dataclass(frozen=True)
class SlideRead:
    """One verified read of a scenario's levels of a bundle (:func:`read_slide`): ``bundle`` holds the chosen levels
    coarsest first (its metadata reordered to match; dense level arrays memory-mapped, read-only), ``chosen`` their
    bundle level indices (coarsest first), ``load_features`` whether the feature grid is to be read."""

    bundle: Bundle
    metadata: BundleMetadata  # the bundle's own metadata (all levels, finest first)
    chosen: list[int]
    load_features: bool
    verify: bool

    def feature_levels(self) -> tuple[list[np.ndarray], int]:
        """The verified feature grids ``[(gh, gw, D) floats]`` of the chosen levels (coarsest first) and the grid
        stride (px of a level); read on demand, so a caller packing the pixels first holds one copy at a time."""
        return load_feature_levels(self.bundle.path, self.metadata, self.chosen, verify=self.verify)


def read_slide(
    path,
    n_levels: int,
    *,
    verify: bool = True,
    pixels: bool = True,
    features: bool | None = None,
    check: Callable[[BundleMetadata, list[int], bool], None] | None = None,
    use: Callable[[SlideRead], object] | None = None,
):
    """The verified read of ``n_levels`` zoom levels of the bundle at ``path``: ``metadata.json`` read and checked
    (digest too with ``verify``), the levels chosen (:func:`~data_tools.bundle_files.format.select_levels`, coarsest
    first) and refused when zooming between them would do nothing (:func:`check_levels`) or when ``pixels`` is
    asked of a feature-only bundle, ``check(metadata, chosen, load_features)`` called before any array is read (a
    caller's budget: it raises to refuse), then the level arrays read (checksums verified with ``verify``;
    memory-mapped). ``features``: ``None`` reads the feature grid if the bundle has one, ``True`` requires it,
    ``False`` skips it (``pixels=False`` always reads it). The whole read, and ``use(read)`` if given, is repeated
    when a rebuild swaps the folder meanwhile (:func:`stable_read`). Returns ``use(read)``, or the
    :class:`SlideRead` without ``use``."""
    path = Path(path)

    def attempt():
        metadata = read_metadata(path)
        if verify:
            verify_metadata(path, metadata)
        chosen = select_levels(metadata, n_levels, path)
        check_levels(path, metadata, chosen)
        load_features = bool(features) or (features is None and bool(metadata.features)) or not pixels
        missing = [k for k in chosen if k not in metadata.pixel_levels]
        if pixels and missing:
            raise BundleError(
                path,
                f"keeps no pixels at bundle levels {sorted(missing)} (a feature-only bundle, made {_pixels_hint(path)}",
            )
        if check is not None:
            check(metadata, chosen, load_features)
        coarsest = len(metadata.levels) - 1
        if chosen[0] != coarsest:
            raise BundleError(path, "the scenario's coarsest level is not the bundle's coarsest; rebuild the bundle")
        bundle = load_bundle(path, verify=verify, levels=chosen, mmap=True, metadata=metadata)
        ordered = Bundle(
            path=bundle.path,
            metadata=metadata.with_levels(chosen),
            pixels=bundle.pixels,
            tumour=bundle.tumour,
            tissue=bundle.tissue,
            region=bundle.region,
        )
        read = SlideRead(
            bundle=ordered, metadata=metadata, chosen=list(chosen), load_features=load_features, verify=verify
        )
        return read if use is None else use(read)

    return stable_read(path, attempt)
