"""The embedded sample slide (CMU-1-Small-Region.svs, CC0) and its bundle, built on first use.

The annotation shipped with it is an illustrative *navigation target* drawn on visible
epithelium for the demo — not a diagnosis.
"""

from __future__ import annotations

from pathlib import Path

from histojax.cache import cache_dir, cached_bundle  # noqa: F401  (cache_dir: re-exported)

DATA = Path(__file__).parent / "data"
SAMPLE_SLIDE = DATA / "CMU-1-Small-Region.svs"
SAMPLE_ANNOTATIONS = DATA / "CMU-1-Small-Region.target.xml"


def sample_bundle(tile_size: int = 128, progress: bool = True) -> Path:
    """Path to the bundle of the embedded sample slide at ``tile_size`` px views (levels for
    3, 5 and 7 zoom levels), building it into the cache the first time (a few seconds)."""
    from data_tools.bundle_files.format import FORMAT_VERSION, text_digest

    digest = text_digest(SAMPLE_SLIDE.read_bytes() + SAMPLE_ANNOTATIONS.read_bytes(), 12)
    return cached_bundle(
        SAMPLE_SLIDE,
        SAMPLE_ANNOTATIONS,
        tile_size=tile_size,
        progress=progress,
        storage="dense",
        name=f"cmu-1-small-region-t{tile_size}-v{FORMAT_VERSION}-{digest}",
    )


def sample_feature_bundle() -> Path:
    """A copy of the cached sample bundle with an EfficientNet-Lite0 feature grid, computed on first
    use (about a minute and a half on 2 CPU cores; needs the ``features`` extra)."""
    import shutil
    import time

    from data_tools.bundle_files.reading import read_metadata
    from data_tools.bundle_files.writes import atomic_folder
    from data_tools.features.grid import compute_features

    source = sample_bundle()
    out = source.with_name(source.name + "-features")
    if not (out.is_dir() and read_metadata(out).features):
        if not out.is_dir():
            with atomic_folder(out) as tmp:
                shutil.copytree(source, tmp, dirs_exist_ok=True)
        t0 = time.perf_counter()
        compute_features(out)
        print(f"computed the feature grid of {out} in {time.perf_counter() - t0:.1f} s")
    return out
