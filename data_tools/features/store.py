"""Feature grids inside a slide bundle: the grid geometry, atomic writes, and loading.

For each bundle level ``KK`` (finest first, as in ``metadata["levels"]``), ``features_KK.npy`` is a
``(gh, gw, D)`` array: cell ``(gy, gx)`` describes the view (``tile_size`` px square) whose
top-left corner is ``(gx · stride, gy · stride)`` px of that level, for ``gx = 0 … gw − 1`` with
``gw = (W − tile_size) // stride + 1`` (likewise ``gh``), ``W × H`` the level's size. ``stride``
defaults to ``tile_size`` (views side by side). ``metadata["features"]`` records the encoder, ``dim``,
``stride``, the projection and one entry per level (file, grid shape, optional mask file); every
file's SHA-256 goes into ``metadata["checksums"]``. Files are written to a temporary name and
``os.replace``-d; ``metadata.json`` last, the same way.
"""
from __future__ import annotations

import json
import os
import uuid
from pathlib import Path

import numpy as np

from data_tools.bundle import METADATA, _load_array, _sha256, read_metadata
from data_tools.errors import BundleError

FEATURES_COMMAND = "python -m data_tools features BUNDLE"


def grid_shape(width: int, height: int, tile_size: int, stride: int) -> tuple[int, int]:
    """``(gh, gw)``: grid positions of views inside a ``width × height`` level (see the module doc)."""
    if stride < 1:
        raise ValueError(f"stride must be at least 1 px, got {stride}")
    return max(0, (height - tile_size) // stride + 1), max(0, (width - tile_size) // stride + 1)


def level_grids(metadata: dict, stride: int) -> list[tuple[int, int]]:
    """``(gh, gw)`` of every bundle level (finest first)."""
    t = int(metadata["tile_size"])
    return [grid_shape(int(lv["width"]), int(lv["height"]), t, stride) for lv in metadata["levels"]]


def save_array(path: Path, array: np.ndarray) -> None:
    """``np.save`` to a temporary sibling, fsync, then ``os.replace`` (readers never see half a file)."""
    tmp = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    try:
        with open(tmp, "wb") as f:
            np.save(f, array, allow_pickle=False)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def update_metadata(bundle: Path, features: dict, written: list[str]) -> dict:
    """Set ``metadata["features"]``, record the SHA-256 of the ``written`` files, drop the files (and
    checksums) of an earlier feature grid that the new one no longer uses, and replace
    ``metadata.json`` atomically (temporary file + ``os.replace``). Returns the new metadata."""
    bundle = Path(bundle)
    metadata = read_metadata(bundle)
    old = _feature_files(metadata.get("features"))
    new = _feature_files(features)
    checksums = {k: v for k, v in metadata["checksums"].items() if k not in old - new}
    checksums.update({name: _sha256(bundle / name) for name in written})
    metadata = {**metadata, "features": features, "checksums": checksums}
    tmp = bundle / f".{METADATA}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        with open(tmp, "w") as f:
            json.dump(metadata, f, indent=1)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, bundle / METADATA)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    for name in old - new:
        (bundle / name).unlink(missing_ok=True)
    return metadata


def _feature_files(features: dict | None) -> set[str]:
    if not features:
        return set()
    files = set()
    for lv in features.get("levels", []):
        files.add(lv["file"])
        if lv.get("mask_file"):
            files.add(lv["mask_file"])
    projection = features.get("projection") or {}
    for key in ("file", "mean_file"):
        if projection.get(key):
            files.add(projection[key])
    return files


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
        array = _load_array(bundle, entry["file"], metadata, verify)
        if array.shape != (*expected[k], dim) or array.dtype.kind != "f":
            raise BundleError(bundle / entry["file"], f"feature grid of shape {array.shape} ({array.dtype}), expected "
                              f"{(*expected[k], dim)} floats; recompute it with `{FEATURES_COMMAND}`")
        arrays.append(array)
    return arrays, stride


__all__ = ["grid_shape", "level_grids", "load_feature_levels", "save_array", "update_metadata"]
