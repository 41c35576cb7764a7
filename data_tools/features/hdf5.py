"""Import patch features made elsewhere (CLAM / TRIDENT HDF5) onto a bundle's feature grid
(``python -m data_tools import-features BUNDLE FILE.h5 --patch-size P --level L``).

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
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from data_tools.bundle_format import read_metadata, sha256
from data_tools.errors import BundleError, HistojaxDataError
from data_tools.features.store import level_grids, save_array, update_metadata


class FeatureFileError(HistojaxDataError):
    """An HDF5 feature file is missing datasets, has inconsistent shapes or non-finite values."""


def _attr(dataset, name):
    value = dataset.attrs.get(name)
    if value is None:
        return None
    value = np.asarray(value).ravel()
    return float(value[0]) if value.size else None


def read_patch_features(path, patch_size: int | None = None, level: int | None = None,
                        downsample: float | None = None):
    """``(coords (N, 2) float64 level-0 px, features (N, D) float32, extent E in level-0 px, info)``."""
    import h5py

    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except (OSError, ValueError) as e:
        raise FeatureFileError(path, f"not a readable HDF5 file ({e})") from None
    with f:
        for name in ("coords", "features"):
            if name not in f or not isinstance(f[name], h5py.Dataset):
                raise FeatureFileError(path, f"no {name!r} dataset (expected CLAM/TRIDENT layout: coords (N, 2), "
                                       "features (N, D))")
        coords_ds = f["coords"]
        coords = np.asarray(coords_ds[()], dtype=np.float64)
        features = np.asarray(f["features"][()], dtype=np.float32)
        attrs = {k: _attr(coords_ds, k) for k in ("patch_size", "patch_level", "downsample", "patch_size_level0")}
    if features.ndim == 3 and features.shape[0] == 1:
        features = features[0]
    if coords.ndim == 3 and coords.shape[0] == 1:
        coords = coords[0]
    if coords.ndim != 2 or coords.shape[1] != 2 or features.ndim != 2 or len(coords) != len(features):
        raise FeatureFileError(path, f"coords {coords.shape} and features {features.shape} do not match "
                               "(expected (N, 2) and (N, D))")
    if not (np.isfinite(coords).all() and np.isfinite(features).all()):
        raise FeatureFileError(path, "coords or features hold NaN or infinity")
    level = level if level is not None else attrs["patch_level"]
    if patch_size is None and attrs["patch_size_level0"]:  # TRIDENT
        extent = attrs["patch_size_level0"]
    else:
        patch_size = patch_size if patch_size is not None else attrs["patch_size"]
        if patch_size is None:
            raise FeatureFileError(path, "patch size unknown: pass --patch-size P (px at --level L)")
        level = int(level or 0)
        ds = downsample if downsample is not None else attrs["downsample"]
        if ds is None:
            if level != 0:
                raise FeatureFileError(path, f"the downsample of pyramid level {level} is unknown: pass --downsample")
            ds = 1.0
        extent = float(patch_size) * float(ds)
    if not (math.isfinite(extent) and extent > 0):
        raise FeatureFileError(path, f"patch extent {extent} level-0 px is not positive")
    info = {"patch_size": patch_size, "level": level, "extent_level0": extent}
    return coords, features, extent, info


def patches_to_grid(coords: np.ndarray, features: np.ndarray, extent: float, grid: tuple[int, int],
                    view0: float, step0: float) -> tuple[np.ndarray, np.ndarray]:
    """Overlap-weighted average of patch features on one level's grid: ``((gh, gw, D) float32, (gh, gw) bool)``.
    ``view0`` / ``step0``: the view's side and the grid step, both in level-0 px."""
    import scipy.sparse as sp

    gh, gw = grid
    d = features.shape[1]
    if gh * gw == 0 or len(coords) == 0:
        return np.zeros((gh, gw, d), np.float32), np.zeros((gh, gw), bool)
    rows, cols, weights = [], [], []
    axes = []
    for a, g in ((0, gw), (1, gh)):
        c = coords[:, a]
        lo = np.clip(np.floor((c - view0) / step0).astype(np.int64) + 1, 0, None)
        hi = np.clip(np.ceil((c + extent) / step0).astype(np.int64) - 1, None, g - 1)
        axes.append((c, lo, hi))
    (cx, x_lo, x_hi), (cy, y_lo, y_hi) = axes
    span_x = int(max(0, (x_hi - x_lo).max() + 1))
    span_y = int(max(0, (y_hi - y_lo).max() + 1))
    patch = np.arange(len(coords))
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
    matrix = sp.csr_matrix((weights, (rows, cols)), shape=(gh * gw, len(coords)))
    total = np.asarray(matrix.sum(axis=1)).ravel()
    sums = matrix @ features.astype(np.float64)
    mask = total > 0
    out = np.zeros((gh * gw, d), np.float64)
    out[mask] = sums[mask] / total[mask, None]
    return out.reshape(gh, gw, d).astype(np.float32), mask.reshape(gh, gw)


def import_features(bundle, h5_path, patch_size: int | None = None, level: int | None = None,
                    downsample: float | None = None, stride: int | None = None, dtype: str = "float16") -> dict:
    """Map the patch features of ``h5_path`` onto every level of the bundle's grid (see the module doc),
    write ``features_KK.npy`` and ``features_mask_KK.npy``, update the metadata; returns
    ``metadata["features"]``."""
    bundle, h5_path = Path(bundle), Path(h5_path)
    metadata = read_metadata(bundle)
    if dtype not in ("float16", "float32"):
        raise BundleError(bundle, f"dtype must be float16 or float32, got {dtype!r}")
    tile = metadata.tile_size
    stride = int(stride or tile)
    coords, features, extent, info = read_patch_features(h5_path, patch_size, level, downsample)
    if (metadata.region or {}).get("box"):  # a region bundle's level-0 px start at the region's corner
        coords = coords - np.asarray(metadata.region_offset, dtype=np.float64)
        info["region_offset"] = list(metadata.region_offset)
    written, levels = [], []
    for k, (lv, grid) in enumerate(zip(metadata.levels, level_grids(metadata, stride))):
        d = lv.downsample
        grid_features, mask = patches_to_grid(coords, features, extent, grid, tile * d, stride * d)
        names = {"file": f"features_{k:02d}.npy", "mask_file": f"features_mask_{k:02d}.npy"}
        save_array(bundle / names["file"], grid_features.astype(dtype))
        save_array(bundle / names["mask_file"], mask)
        written += [names["file"], names["mask_file"]]
        levels.append({**names, "grid": list(grid), "covered": int(mask.sum())})
    result = {
        "encoder": f"imported:{h5_path.name}", "dim": int(features.shape[1]), "stride": stride, "dtype": dtype,
        "projection": None, "source": "imported",
        "import": {"file": h5_path.name, "sha256": sha256(h5_path), "n_patches": int(len(coords)), **info},
        "grid": "cell (gy, gx) of level KK = the view with top-left (gx*stride, gy*stride) px of that level",
        "levels": levels,
    }
    update_metadata(bundle, result, written)
    return result


__all__ = ["FeatureFileError", "import_features", "patches_to_grid", "read_patch_features"]
