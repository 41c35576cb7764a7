"""Building a bundle into the cache once: the one place histojax calls the bundle writer.

The embedded sample slide (:mod:`histojax.sample`), scenario files (:mod:`histojax.scenarios`) and
HistoGym's API (:mod:`histojax.adapters.histogym`) all turn a slide
file into a bundle folder under :func:`cache_dir` named by a digest of the inputs and every build
setting, built the first time and reused after. Concurrent builders of one bundle wait on the build lock
(:func:`data_tools.bundle.build_lock`); the losers find it built and return it.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

from data_tools.bundle_files.format import FORMAT_VERSION, LEVEL_SETS, METADATA, file_digest, text_digest
from data_tools.errors import BundleError


def cache_dir() -> Path:
    """Where built bundles are cached: ``$HISTOJAX_CACHE`` or ``~/.cache/histojax``."""
    return Path(os.environ.get("HISTOJAX_CACHE", Path.home() / ".cache" / "histojax"))


def _sealed(bundle: Path) -> bool:
    """True when the bundle's ``metadata.json`` carries its digest (built by this version of histojax)."""
    from data_tools.bundle_files.seals import METADATA_DIGEST

    try:
        return METADATA_DIGEST in json.loads((bundle / METADATA).read_text())
    except (OSError, ValueError):
        return True  # unreadable: let the loader say what is wrong with it


def cached_bundle(
    slide,
    annotations=None,
    tile_size: int = 128,
    level_sets=None,
    label_map=None,
    region=None,
    prefix: str = "scenario",
    progress: bool = False,
    storage: str = "auto",
    name: str | None = None,
) -> Path:
    """Build (once) and return the bundle of ``slide`` (+ ``annotations``) in the cache folder
    ``cache_dir() / f"{prefix}-{sha}"``, where the digest covers the files and every build setting
    (``name`` gives the folder name instead). ``tile_size`` is the view size in px, ``level_sets`` the
    scenario level counts (default 3, 5 and 7), ``region`` a :class:`histojax.scenarios.RegionRule`,
    ``storage`` as in :func:`data_tools.bundle.build_bundle` (``"auto"``: tiled when the dense levels
    would exceed 256 MiB on the device)."""
    from data_tools.bundle import build_bundle

    level_sets = tuple(sorted(level_sets or LEVEL_SETS))
    if name is None:
        key = json.dumps(  # json-not-written (a cache key)
            {
                "slide": file_digest(slide),
                "annotations": None if annotations is None else file_digest(annotations),
                "tile_size": tile_size,
                "levels": level_sets,
                "label_map": label_map,
                "region": None if region is None else dataclasses.asdict(region),
                "format": FORMAT_VERSION,
                "storage": storage,
            },
            sort_keys=True,
        )
        name = f"{prefix}-{text_digest(key)}"
    out = cache_dir() / name
    if not (out / METADATA).is_file() or not _sealed(out):
        try:  # a cached bundle built before metadata was sealed is rebuilt (replaced atomically)
            build_bundle(
                slide,
                out,
                annotations_path=annotations,
                level_sets=level_sets,
                tile_size=tile_size,
                label_map=label_map,
                progress=progress,
                overwrite=(out / METADATA).is_file(),
                region=None if region is None else region.build_argument(),
                region_margin=0.0 if region is None else region.margin,
                storage=storage,
            )
        except BundleError:
            if not (out / METADATA).is_file():  # another process may have just built it
                raise
    return out


__all__ = ["cache_dir", "cached_bundle"]
