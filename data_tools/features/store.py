"""Feature grids inside a slide bundle: writing them (the grid geometry, the atomic file writes and the
verified read are the bundle format's, :mod:`data_tools.bundle_files`, re-exported here).

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

from pathlib import Path

from data_tools.bundle_files.format import FEATURES_COMMAND, grid_shape, level_grids, sha256  # noqa: F401  (re-exported: grid geometry, atomic save and the read)
from data_tools.bundle_files.reading import load_feature_levels, read_metadata
from data_tools.bundle_files.seals import write_metadata
from data_tools.bundle_files.writes import save_array


def update_metadata(bundle: Path, features: dict, written: list[str]) -> dict:
    """Set ``metadata["features"]``, record the SHA-256 of the ``written`` files, drop the files (and
    checksums) of an earlier feature grid that the new one no longer uses, and replace
    ``metadata.json`` atomically (temporary file + ``os.replace``). Returns the new metadata."""
    bundle = Path(bundle)
    metadata = read_metadata(bundle)
    old = _feature_files(metadata.get("features"))
    new = _feature_files(features)
    checksums = {k: v for k, v in metadata.checksums.items() if k not in old - new}
    checksums.update({name: sha256(bundle / name) for name in written})
    metadata = {**metadata, "features": features, "checksums": checksums}
    write_metadata(bundle, metadata)
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


__all__ = ["grid_shape", "level_grids", "load_feature_levels", "save_array", "update_metadata"]
