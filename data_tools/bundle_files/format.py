"""The slide-bundle format: file names, versions, level geometry, device bytes, the typed view of
``metadata.json`` (:class:`BundleMetadata`) and the checksums.

Why here, in ``data_tools`` (the lower layer, numpy only): data flows one way. ``data_tools``
(offline: slide-file readers, shapely, PIL) *writes* bundles; ``histojax`` (the environment, JAX)
*reads* them. Both need the format, and the reading side must not pull in the writer nor the writer
JAX, so the format is its own package of the lower layer (:mod:`data_tools.bundle_files`), imported by the writer
(:mod:`data_tools.bundle`, :mod:`data_tools.tiled`, :mod:`data_tools.features`) and by every
reader (:mod:`histojax.loading`, :mod:`histojax.render`, :mod:`histojax.cache`); it imports nothing
of either (only the leaf module of error types). Nothing else reads ``metadata.json`` or checks a
checksum.

A bundle is one folder with ``metadata.json`` (:data:`METADATA`) and ``.npy`` arrays. For each
zoom level the environment may use (``metadata["levels"]`` lists them finest first):
  * dense (format version 1): ``pixels_KK.npy`` ``(H, W, 3)`` uint8 RGB and ``tumour_KK.npy``
    ``(H, W)`` uint8 0/1 tumour mask (exclusion holes removed);
  * tiled (format version 2, gigapixel slides): tile pools and index grids per level (see
    :class:`data_tools.bundle_files.reading.TiledLevel` and :mod:`data_tools.tiled`);
plus ``tissue.npy`` (bool, coarsest level), ``annotations.geojson`` (level-0 px), ``region.npy``
(region bundles) and optional feature grids ``features_KK.npy`` (``metadata["features"]``).
Every file's SHA-256 is recorded in ``metadata["checksums"]`` and checked on load; arrays are read
with ``allow_pickle=False``.
"""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import numpy as np

from data_tools.errors import BundleError

__all__ = [
    "ANNOTATIONS",
    "BundleMetadata",
    "FEATURES_COMMAND",
    "FORMAT_VERSION",
    "LEVEL_SETS",
    "LevelMeta",
    "MAX_FLAT_PIXELS",
    "METADATA",
    "READ_VERSIONS",
    "REGION",
    "STORAGES",
    "TILED_FORMAT_VERSION",
    "TISSUE",
    "bundle_downsamples",
    "default_magnification_range",
    "device_bytes",
    "feature_bytes",
    "file_digest",
    "grid_shape",
    "level_device_bytes",
    "level_downsamples",
    "level_files",
    "level_grids",
    "level_size",
    "select_levels",
    "sha256",
    "slide_device_bytes",
    "text_digest",
    "tiled_level_files",
    "tumour_table_bytes",
]


FORMAT_VERSION = 1  # dense bundles (pixels_KK.npy / tumour_KK.npy)


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
    return {
        "tiles": f"tiles_{k:02d}.npy",
        "tile_index": f"tile_index_{k:02d}.npy",
        "sat_tiles": f"sat_tiles_{k:02d}.npy",
        "sat_index": f"sat_index_{k:02d}.npy",
    }


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
            raise BundleError(
                where or None,
                f"bundle has no level at downsample {d:.4g} needed for {n_levels} "
                f"zoom levels (it was built for {metadata.get('level_sets')}); rebuild with "
                f"`python -m data_tools build ... --levels {n_levels}`",
            )
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
        raise BundleError(
            where, "metadata['features'] is malformed; recompute with `python -m data_tools features BUNDLE`"
        ) from None


def tumour_table_bytes(level: dict, tile_size: int) -> int:
    """Device bytes of one bundle level's tumour table alone (no pixels): the tiled SAT pool and its index
    grid, or the dense level's uint32 summed-area table."""
    if level.get("storage") == "tiled":
        gh, gw = level["grid"]
        return int(level["sat_pool_tiles"]) * (tile_size + 1) ** 2 * 4 + 4 * int(gh) * int(gw)
    return 4 * (int(level["width"]) + 1) * (int(level["height"]) + 1)


def slide_device_bytes(
    metadata: dict, chosen: list[int], pixels: bool = True, features: bool = False, where=None
) -> int:
    """Device bytes of bundle levels ``chosen`` (from the metadata, nothing read): pixels and tumour tables
    (``pixels=False``: tumour tables only), plus the feature grids when ``features``; start weights are
    small (the coarsest level) and not counted."""
    t = int(metadata["tile_size"])
    if pixels:
        needed = sum(level_device_bytes(metadata["levels"][k]) for k in chosen)
        if metadata.get("storage") == "tiled":
            needed += 3 * t**2  # the spare tile at the end of the pool
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
