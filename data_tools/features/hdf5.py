"""Import patch features made elsewhere (CLAM / TRIDENT HDF5) onto a bundle's feature grid
(``python -m data_tools import-features BUNDLE FILE.h5 --patch-size P --patch-level L``).

The file holds ``coords`` ``(N, 2)`` — each patch's top-left corner ``(x, y)`` in level-0 px of
the slide — and ``features`` ``(N, D)`` (a leading batch axis of 1, as some CLAM versions write, is
dropped). A patch is ``P`` px of pyramid level ``L`` wide, i.e. ``E = P · downsample(L)`` level-0 px;
``downsample(L)`` comes from ``--downsample``, else the ``downsample`` attribute CLAM writes on
``coords``, else 1 for ``L = 0``; TRIDENT's ``patch_size_level0`` attribute gives ``E`` directly. ``P``
and ``L`` default to the ``patch_size`` / ``patch_level`` attributes when present.

Mapping: the grid cell ``(gy, gx)`` of bundle level ``k`` (downsample ``d``) is the view covering
level-0 px ``[gx·s·d, gx·s·d + T·d) × [gy·s·d, gy·s·d + T·d)``; its feature is the average of the
patches overlapping it, weighted by the overlap area (at fine levels, where a view is smaller than a
patch, this is the patch under the view, or a blend of the few it straddles; at coarse levels, the
mean of the patches it covers). Cells no patch touches get zeros and ``False`` in
``features_mask_KK.npy``. For a region bundle (``build --region``) the coordinates are shifted by
the region's corner first.

Bounds, checked from the file's shapes and attributes before its data is read: numeric ``coords`` and
``features`` with ``N ≥ 1`` and ``D ≥ 1``, coordinates and the patch extent inside ±2^31 level-0 px, and
at most :data:`MAX_IMPORT_BYTES` (4 GiB) of host memory for the features, the patch–view overlaps and
the grids; a patch larger than the whole slide, or a file whose patches all miss it, is refused; one covering under
:data:`MIN_TISSUE_COVERAGE` (50 %) of the finest level's tissue views gives a warning.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from data_tools.bundle_files.format import sha256
from data_tools.bundle_files.reading import read_metadata
from data_tools.errors import BundleError, HistojaxDataError
from data_tools.features.store import level_grids, save_array, update_metadata


class FeatureFileError(HistojaxDataError):
    """An HDF5 feature file is missing datasets, has inconsistent shapes or non-finite values."""


MAX_IMPORT_BYTES = 4 * 2**30
"""Host memory an import may use (4 GiB): the ``(N, D)`` features as float32 plus the patch–view overlap
table, and one level's ``(gh, gw, D)`` grid, are estimated from the file's shapes before anything is read;
a file that would need more is refused naming it (``max_bytes=`` raises or lowers the bound)."""
MAX_COORDINATE = 2**31
"""Patch coordinates beyond ±2^31 level-0 px are refused (wrong units: no slide is that large)."""
MIN_TISSUE_COVERAGE = 0.5
"""Below this share of the finest level's tissue views covered by some patch, the import warns (coordinates
in other units, or another slide's file)."""
OVERLAP_ENTRY_BYTES = 64  # host bytes per (patch, view) overlap while the grid is built


def _attr(path, dataset, name):
    value = dataset.attrs.get(name)
    if value is None:
        return None
    try:
        value = np.asarray(value, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise FeatureFileError(path, f"the {name!r} attribute of coords is not a number ({value!r:.40})") from None
    if value.size and not math.isfinite(value[0]):
        raise FeatureFileError(path, f"the {name!r} attribute of coords is {value[0]}")
    return float(value[0]) if value.size else None


def _layout(path: Path, f) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The shapes of ``coords`` and ``features`` (a leading axis of 1 dropped), checked before any data is read."""
    h5py = _h5py(path)

    shapes = {}
    for name in ("coords", "features"):
        ds = f.get(name) if name in f else None
        if not isinstance(ds, h5py.Dataset):
            raise FeatureFileError(
                path, f"no {name!r} dataset (expected CLAM/TRIDENT layout: coords (N, 2), features (N, D))"
            )
        if ds.dtype.kind not in "iuf":
            raise FeatureFileError(
                path,
                f"{name} are not numbers (HDF5 type {ds.dtype}): expected coords (N, 2) and "
                "features (N, D) of integers or floats",
            )
        shape = tuple(int(v) for v in ds.shape or ())
        shapes[name] = shape[1:] if len(shape) == 3 and shape[0] == 1 else shape
    coords, features = shapes["coords"], shapes["features"]
    if len(coords) != 2 or coords[1] != 2 or len(features) != 2 or coords[0] != features[0]:
        raise FeatureFileError(
            path, f"coords {coords} and features {features} do not match (expected (N, 2) and (N, D))"
        )
    if coords[0] == 0:
        raise FeatureFileError(path, "holds no patches (N = 0): an empty feature file")
    if features[1] == 0:
        raise FeatureFileError(path, f"features have D = 0 dimensions ({coords[0]} patches of nothing)")
    return coords, features


def _h5py(path):
    """The ``h5py`` module, or one line naming ``path`` and the extra that installs it (``histojax[features]``)."""
    from data_tools.extras import import_optional

    return import_optional("h5py", "reading CLAM / TRIDENT .h5 features", path)


def _open(path: Path):
    import os
    import stat

    h5py = _h5py(path)

    try:
        st = os.stat(path)
    except OSError as e:
        raise FeatureFileError(path, f"cannot read the feature file ({e.strerror or e})") from None
    if not stat.S_ISREG(st.st_mode):
        raise FeatureFileError(path, "not a regular file (a folder, FIFO or device): not a feature file")
    try:
        return h5py.File(path, "r")
    except Exception as e:  # noqa: BLE001 - h5py raises OSError, ValueError, KeyError ... on damaged files
        raise FeatureFileError(path, f"not a readable HDF5 file ({type(e).__name__}: {e})") from None


def feature_dim(path) -> int:
    """``D`` of the ``(N, D)`` features of the HDF5 file ``path`` (shapes only, no data read)."""
    path = Path(path)
    with _open(path) as f:
        try:
            return _layout(path, f)[1][1]
        except FeatureFileError:
            raise
        except Exception as e:  # noqa: BLE001 - a damaged HDF5 object header
            raise FeatureFileError(path, f"unreadable HDF5 structure ({type(e).__name__}: {e})") from None


def check_feature_dims(paths) -> None:
    """Refuse feature files of different ``D`` (two encoders mixed in one dataset), naming the first file whose
    ``D`` differs from the first readable file's; files that cannot be read are left to fail on their own slide."""
    first: tuple[int, Path] | None = None
    for p in paths:
        try:
            d = feature_dim(p)
        except FeatureFileError:
            continue
        if first is None:
            first = (d, Path(p))
        elif d != first[0]:
            raise FeatureFileError(
                p,
                f"has D = {d} features but {first[1]} has D = {first[0]}: one dataset takes "
                "one encoder's features; point --features-from at one encoder's folder",
            )


def read_patch_features(
    path,
    patch_size: int | None = None,
    level: int | None = None,
    downsample: float | None = None,
    max_bytes: int = MAX_IMPORT_BYTES,
):
    """``(coords (N, 2) float64 level-0 px, features (N, D) float32, extent E in level-0 px, info)``.
    Shapes, types and the memory the arrays need (at most ``max_bytes``) are checked before reading."""
    path = Path(path)
    with _open(path) as f:
        try:
            (n, _), (_, d) = _layout(path, f)
            need = n * d * 4 + n * 2 * 8
            if need > max_bytes:
                raise FeatureFileError(
                    path,
                    f"{n:,} patches × {d:,} features need {need / 2**30:.1f} GiB of host "
                    f"memory, over the import's limit of {max_bytes / 2**30:.1f} GiB",
                )
            coords_ds = f["coords"]
            attrs = {
                k: _attr(path, coords_ds, k) for k in ("patch_size", "patch_level", "downsample", "patch_size_level0")
            }
            coords = np.asarray(coords_ds.astype(np.float64)[()]).reshape(n, 2)
            features = np.asarray(f["features"].astype(np.float32)[()]).reshape(n, d)
        except FeatureFileError:
            raise
        except MemoryError:
            raise FeatureFileError(path, "out of host memory reading the features") from None
        except Exception as e:  # noqa: BLE001 - h5py / HDF5 filter errors on damaged data
            raise FeatureFileError(path, f"unreadable data ({type(e).__name__}: {e})") from None
    if not (np.isfinite(coords).all() and np.isfinite(features).all()):
        raise FeatureFileError(path, "coords or features hold NaN or infinity")
    if np.abs(coords).max() >= MAX_COORDINATE:
        raise FeatureFileError(
            path,
            f"a coordinate is {coords.flat[np.abs(coords).argmax()]:g}, beyond ±2^31 "
            "level-0 px: coords in other units?",
        )
    level = level if level is not None else attrs["patch_level"]
    if patch_size is None and attrs["patch_size_level0"]:  # TRIDENT
        extent = attrs["patch_size_level0"]
    else:
        patch_size = patch_size if patch_size is not None else attrs["patch_size"]
        if patch_size is None:
            raise FeatureFileError(
                path, "patch size unknown: pass --patch-size P (px at pyramid level --patch-level L)"
            )
        if not (level is None or (float(level) == int(level) and 0 <= level < 64)):
            raise FeatureFileError(path, f"patch level {level} is not a pyramid level (0, 1, 2 ...)")
        level = int(level or 0)
        ds = downsample if downsample is not None else attrs["downsample"]
        if ds is None:
            if level != 0:
                raise FeatureFileError(
                    path,
                    f"the downsample of pyramid level {level} is unknown: pass --downsample "
                    "(import-features) or write the 'downsample' attribute on coords",
                )
            ds = 1.0
        extent = float(patch_size) * float(ds)
    if not (math.isfinite(extent) and 0 < extent < MAX_COORDINATE):
        raise FeatureFileError(
            path, f"patch extent {extent:g} level-0 px is not in (0, 2^31): is the patch size right?"
        )
    info = {"patch_size": patch_size, "level": level, "extent_level0": extent}
    return coords, features, extent, info


def _spans(coords, extent, g, a, view0, step0):
    c = coords[:, a]
    lo = np.clip(np.floor((c - view0) / step0).astype(np.int64) + 1, 0, None)
    hi = np.clip(np.ceil((c + extent) / step0).astype(np.int64) - 1, None, g - 1)
    return c, lo, hi


def overlap_count(coords: np.ndarray, extent: float, grid: tuple[int, int], view0: float, step0: float) -> float:
    """How many (patch, view) overlaps :func:`patches_to_grid` would hold (as a float: never overflows);
    computed from ``N`` numbers, before anything grid-sized is allocated."""
    gh, gw = grid
    if gh * gw == 0 or len(coords) == 0:
        return 0.0
    _, x_lo, x_hi = _spans(coords, extent, gw, 0, view0, step0)
    _, y_lo, y_hi = _spans(coords, extent, gh, 1, view0, step0)
    return float(
        np.sum(
            np.clip(x_hi - x_lo + 1, 0, None).astype(np.float64) * np.clip(y_hi - y_lo + 1, 0, None).astype(np.float64)
        )
    )


def patches_to_grid(
    coords: np.ndarray, features: np.ndarray, extent: float, grid: tuple[int, int], view0: float, step0: float
) -> tuple[np.ndarray, np.ndarray]:
    """Overlap-weighted average of patch features on one level's grid: ``((gh, gw, D) float32, (gh, gw) bool)``.
    ``view0`` / ``step0``: the view's side and the grid step, both in level-0 px."""
    import scipy.sparse as sp

    gh, gw = grid
    d = features.shape[1]
    if gh * gw == 0 or len(coords) == 0:
        return np.zeros((gh, gw, d), np.float32), np.zeros((gh, gw), bool)
    cx, x_lo, x_hi = _spans(coords, extent, gw, 0, view0, step0)
    cy, y_lo, y_hi = _spans(coords, extent, gh, 1, view0, step0)
    span_x = int(max(0, (x_hi - x_lo).max() + 1))
    span_y = int(max(0, (y_hi - y_lo).max() + 1))
    patch = np.arange(len(coords))
    rows, cols, weights = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)], [np.zeros(0)]
    for oy in range(span_y):
        gy = y_lo + oy
        wy = np.minimum(gy * step0 + view0, cy + extent) - np.maximum(gy * step0, cy)
        for ox in range(span_x):
            gx = x_lo + ox
            wx = np.minimum(gx * step0 + view0, cx + extent) - np.maximum(gx * step0, cx)
            ok = (gx <= x_hi) & (gy <= y_hi) & (wx > 0) & (wy > 0)
            rows.append(gy[ok] * gw + gx[ok])
            cols.append(patch[ok])
            weights.append(wx[ok] * wy[ok])
    rows, cols, weights = np.concatenate(rows), np.concatenate(cols), np.concatenate(weights)
    total = np.bincount(rows, weights=weights, minlength=gh * gw)
    mask = total > 0
    # each view's weights normalised to sum 1, so one float32 product gives the averages
    matrix = sp.csr_matrix(((weights / total[rows]).astype(np.float32), (rows, cols)), shape=(gh * gw, len(coords)))
    out = np.asarray(matrix @ np.asarray(features, np.float32), dtype=np.float32)
    out[~mask] = 0
    return out.reshape(gh, gw, d), mask.reshape(gh, gw)


def tissue_coverage(bundle: Path, metadata, mask: np.ndarray, level: int, stride: int) -> tuple[int, int] | None:
    """``(covered, total)``: of the views of bundle level ``level`` that are at least half tissue (the bundle's
    tissue mask), how many ``mask`` marks covered; on a slide of scattered tissue where no view is half tissue,
    of the views holding any tissue; None when that level has no view touching tissue."""
    tissue = np.load(bundle / metadata.tissue_file, allow_pickle=False).astype(bool)
    th, tw = tissue.shape
    table = np.zeros((th + 1, tw + 1), np.int64)
    table[1:, 1:] = tissue.cumsum(0).cumsum(1)
    scale = metadata.levels[level].downsample / metadata.levels[-1].downsample  # level px -> tissue px
    gh, gw = mask.shape
    x0 = np.clip(np.floor(np.arange(gw) * stride * scale).astype(np.int64), 0, tw)
    x1 = np.clip(np.ceil((np.arange(gw) * stride + metadata.tile_size) * scale).astype(np.int64), 0, tw)
    y0 = np.clip(np.floor(np.arange(gh) * stride * scale).astype(np.int64), 0, th)
    y1 = np.clip(np.ceil((np.arange(gh) * stride + metadata.tile_size) * scale).astype(np.int64), 0, th)
    inside = table[y1][:, x1] - table[y0][:, x1] - table[y1][:, x0] + table[y0][:, x0]
    area = np.maximum((y1 - y0)[:, None] * (x1 - x0)[None, :], 1)
    views = inside / area >= 0.5
    if not views.any():  # scattered tissue (a few % of the slide): every view holding some
        views = inside > 0
    if not views.any():
        return None
    return int((views & mask).sum()), int(views.sum())


def imported_encoder(h5_path) -> str:
    """The encoder name features imported from ``h5_path`` record: ``imported:`` and the file's folder with the one
    above it, the layout the exporting tool wrote (TRIDENT ``20x_256px_0px_overlap/features_uni_v1/*.h5``, CLAM
    ``RESULTS/h5_files/*.h5``), so that two encoders' features of one length stay apart and every slide of one
    import records one name (its own file is ``import.file``)."""
    folder = Path(h5_path).resolve().parent
    parts = [p for p in (folder.parent.name, folder.name) if p]
    return f"imported:{'/'.join(parts) or '.'}/*.h5"


def import_features(
    bundle,
    h5_path,
    patch_size: int | None = None,
    level: int | None = None,
    downsample: float | None = None,
    stride: int | None = None,
    dtype: str = "float16",
    max_bytes: int = MAX_IMPORT_BYTES,
) -> dict:
    """Map the patch features of ``h5_path`` onto every level of the bundle's grid (see the module doc),
    write ``features_KK.npy`` and ``features_mask_KK.npy``, update the metadata; returns
    ``metadata["features"]`` (its ``import`` record holds ``tissue_coverage``: covered and total tissue views
    of the finest level). Refused, naming the file, before anything is written: a file needing more than
    ``max_bytes`` of host memory (see :data:`MAX_IMPORT_BYTES`), or whose patches miss the slide entirely;
    a warning when they cover less than :data:`MIN_TISSUE_COVERAGE` of the tissue views."""
    import warnings

    bundle, h5_path = Path(bundle), Path(h5_path)
    metadata = read_metadata(bundle)
    if dtype not in ("float16", "float32"):
        raise BundleError(bundle, f"dtype must be float16 or float32, got {dtype!r}")
    tile = metadata.tile_size
    stride = int(stride or tile)
    coords, features, extent, info = read_patch_features(h5_path, patch_size, level, downsample, max_bytes)
    if (metadata.region or {}).get("box"):  # a region bundle's level-0 px start at the region's corner
        coords = coords - np.asarray(metadata.region_offset, dtype=np.float64)
        info["region_offset"] = list(metadata.region_offset)
    side = max(float(metadata.source.get("width") or 0), float(metadata.source.get("height") or 0))
    if side > 0 and extent > side:
        raise FeatureFileError(
            h5_path,
            f"a patch of {extent:g} level-0 px is larger than the whole slide "
            f"({metadata.source.get('width')}×{metadata.source.get('height')} level-0 px): "
            "is the patch size (--patch-size / the patch_size attribute) right?",
        )
    grids = level_grids(metadata, stride)
    n, dim = features.shape
    base = features.nbytes + coords.nbytes
    cells = sum(gh * gw for gh, gw in grids)
    for lv, grid in zip(metadata.levels, grids):
        d = lv.downsample
        pairs = overlap_count(coords, extent, grid, tile * d, stride * d)
        need = base + pairs * OVERLAP_ENTRY_BYTES + cells * dim * (4 + np.dtype(dtype).itemsize)
        if need > max_bytes:
            raise FeatureFileError(
                h5_path,
                f"its {n:,} patches of {extent:g} level-0 px overlap {pairs:,.0f} views "
                f"of a {grid[0]}×{grid[1]} grid: {need / 2**30:.1f} GiB of host memory, "
                f"over the import's limit of {max_bytes / 2**30:.1f} GiB; is the patch "
                "size (--patch-size / the patch_size attribute) right?",
            )
    computed = []
    for lv, grid in zip(metadata.levels, grids):
        d = lv.downsample
        computed.append(patches_to_grid(coords, features, extent, grid, tile * d, stride * d))
    if not any(mask.any() for _, mask in computed):
        w0 = metadata.levels[0].width * metadata.levels[0].downsample
        h0 = metadata.levels[0].height * metadata.levels[0].downsample
        lo, hi = coords.min(axis=0), coords.max(axis=0)
        raise FeatureFileError(
            h5_path,
            f"none of its {n:,} patches lies on the slide ({w0:.0f}×{h0:.0f} level-0 px; "
            f"coords span x {lo[0]:g}..{hi[0]:g}, y {lo[1]:g}..{hi[1]:g}): coords of "
            "another slide, or not in level-0 px?",
        )
    if dtype == "float16":
        top = max(float(np.abs(g).max(initial=0.0)) for g, _ in computed)
        if top > float(np.finfo(np.float16).max):
            raise FeatureFileError(
                h5_path,
                f"feature values reach {top:.3g}, beyond float16's ±65504 (they would be "
                "stored as infinity): scale the features, or import-features --dtype "
                "float32",
            )
    coverage = tissue_coverage(bundle, metadata, computed[0][1], 0, stride)
    info["tissue_coverage"] = None if coverage is None else list(coverage)
    if coverage is not None and coverage[0] < MIN_TISSUE_COVERAGE * coverage[1]:
        warnings.warn(
            f"{h5_path}: its patches cover {coverage[0]} of the {coverage[1]} tissue views of the finest "
            f"level ({coverage[0] / coverage[1]:.0%}, under {MIN_TISSUE_COVERAGE:.0%}): coords not in "
            "level-0 px of this slide, or the wrong patch size?",
            stacklevel=2,
        )
    written, levels = [], []
    for k, (grid, (grid_features, mask)) in enumerate(zip(grids, computed)):
        names = {"file": f"features_{k:02d}.npy", "mask_file": f"features_mask_{k:02d}.npy"}
        save_array(bundle / names["file"], grid_features.astype(dtype))
        save_array(bundle / names["mask_file"], mask)
        written += [names["file"], names["mask_file"]]
        levels.append({**names, "grid": list(grid), "covered": int(mask.sum())})
    result = {
        "encoder": imported_encoder(h5_path),
        "dim": int(dim),
        "stride": stride,
        "dtype": dtype,
        "projection": None,
        "source": "imported",
        "import": {"file": h5_path.name, "sha256": sha256(h5_path), "n_patches": int(n), **info},
        "grid": "cell (gy, gx) of level KK = the view with top-left (gx*stride, gy*stride) px of that level",
        "levels": levels,
    }
    update_metadata(bundle, result, written)
    return result


__all__ = [
    "MAX_IMPORT_BYTES",
    "MIN_TISSUE_COVERAGE",
    "FeatureFileError",
    "check_feature_dims",
    "feature_dim",
    "import_features",
    "imported_encoder",
    "overlap_count",
    "patches_to_grid",
    "read_patch_features",
    "tissue_coverage",
]
