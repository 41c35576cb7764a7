"""The embedded sample slide (CMU-1-Small-Region.svs, CC0) and its bundle, built on first use.

The annotation shipped with it is an illustrative *navigation target* drawn on visible
epithelium for the demo — not a diagnosis.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

DATA = Path(__file__).parent / "data"
SAMPLE_SLIDE = DATA / "CMU-1-Small-Region.svs"
SAMPLE_ANNOTATIONS = DATA / "CMU-1-Small-Region.target.xml"


def cache_dir() -> Path:
    """Where built bundles are cached: ``$HISTOJAX_CACHE`` or ``~/.cache/histojax``."""
    return Path(os.environ.get("HISTOJAX_CACHE", Path.home() / ".cache" / "histojax"))


def sample_bundle(tile_size: int = 128, progress: bool = True) -> Path:
    """Path to the bundle of the embedded sample slide at ``tile_size`` px views (levels for
    3, 5 and 7 zoom levels), building it into the cache the first time (a few seconds)."""
    from data_tools.bundle import FORMAT_VERSION, build_bundle
    from data_tools.errors import BundleError

    digest = hashlib.sha256(SAMPLE_SLIDE.read_bytes() + SAMPLE_ANNOTATIONS.read_bytes()).hexdigest()[:12]
    out = cache_dir() / f"cmu-1-small-region-t{tile_size}-v{FORMAT_VERSION}-{digest}"
    if not (out / "metadata.json").is_file():
        try:
            build_bundle(SAMPLE_SLIDE, out, annotations_path=SAMPLE_ANNOTATIONS, tile_size=tile_size,
                         progress=progress)
        except BundleError:
            if not (out / "metadata.json").is_file():  # another process may have just built it
                raise
    return out


def sample_feature_bundle() -> Path:
    """A copy of the cached sample bundle with an EfficientNet-Lite0 feature grid, computed on first
    use (about a minute and a half on 2 CPU cores; needs the ``features`` extra)."""
    import shutil
    import time

    from data_tools.bundle import read_metadata
    from data_tools.features.grid import compute_features

    source = sample_bundle()
    out = source.with_name(source.name + "-features")
    if not (out.is_dir() and read_metadata(out).get("features")):
        if not out.is_dir():
            tmp = out.with_name(out.name + ".copy")
            shutil.rmtree(tmp, ignore_errors=True)
            shutil.copytree(source, tmp)
            tmp.rename(out)
        t0 = time.perf_counter()
        compute_features(out)
        print(f"computed the feature grid of {out} in {time.perf_counter() - t0:.1f} s")
    return out
