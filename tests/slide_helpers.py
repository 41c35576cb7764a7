"""Small slide files for the tests, shared by the test modules that import them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tifffile


def pyramid(path: Path, rgb: np.ndarray, mpp: float = 0.5) -> Path:
    """A 3-level pyramidal tiled TIFF (SubIFDs at 2x, 4x) of ``rgb`` with µm/px in the resolution tags."""
    path.parent.mkdir(parents=True, exist_ok=True)
    levels = [rgb]
    while len(levels) < 3:
        a = levels[-1]
        h, w = a.shape[0] // 2 * 2, a.shape[1] // 2 * 2
        levels.append(a[:h, :w].reshape(h // 2, 2, w // 2, 2, 3).mean((1, 3)).astype(np.uint8))
    ppc = 1e4 / mpp
    with tifffile.TiffWriter(path) as tif:
        opts = dict(tile=(128, 128), photometric="rgb", resolutionunit="CENTIMETER")
        tif.write(levels[0], subifds=2, resolution=(ppc, ppc), **opts)
        for k, lv in enumerate(levels[1:], 1):
            tif.write(lv, subfiletype=1, resolution=(ppc / 2**k, ppc / 2**k), **opts)
    return path


def tiny_feature_bundle(root: Path, seed: int, tile: int = 32) -> Path:
    """A 1024 × 768 px single-level slide (glass, pink tissue, a purple "tumour" block, ±8 noise from
    ``seed``) built into ``root/bundle`` at ``tile``-px views, Easy levels, with the cheap ``colour-stats``
    feature grid (float32); returns the bundle path."""
    from data_tools.bundle import build_bundle
    from data_tools.features.grid import compute_features

    rng = np.random.default_rng(seed)
    image = np.full((768, 1024, 3), 245, np.uint8)  # glass
    image[80:680, 60:940] = [230, 160, 200]  # pink tissue
    image[200:360, 600:840] = [120, 40, 140]  # purple "tumour"
    image = np.clip(image.astype(int) + rng.integers(-8, 9, image.shape), 0, 255).astype(np.uint8)
    tifffile.imwrite(root / "tiny.tif", image, photometric="rgb")
    path = build_bundle(root / "tiny.tif", root / "bundle", level_sets=(3,), tile_size=tile, progress=False)
    compute_features(path, encoder_name="colour-stats", batch=64, progress=False, dtype="float32")
    return path


def synth_feature_dataset(root: Path, n_slides: int, negatives: int) -> Path:
    """A ``data_tools synth`` dataset in ``root`` (``n_slides`` tumour + ``negatives`` normal slides, 320 × 256 px,
    32-px views, Easy's 3 levels, seed 0) with the cheap ``colour-stats`` feature grids; returns ``root``."""
    from baselines.reading.budget_curve import compute_missing_features
    from data_tools.datasets.synth.dataset import make_dataset

    make_dataset(
        root,
        n_slides=n_slides,
        negatives=negatives,
        size=(320, 256),
        seed=0,
        tile_size=32,
        level_sets=(3,),
        progress=False,
        previews=False,
    )
    compute_missing_features(root, "colour-stats")
    return root


def sample_pixels() -> np.ndarray:
    """Level 0 of the embedded sample slide (CMU-1-Small-Region.svs, CC0 1.0): the real pixels stand-in slides are
    cut from."""
    from histojax.sample import SAMPLE_SLIDE

    with tifffile.TiffFile(SAMPLE_SLIDE) as tif:
        return tif.pages[0].asarray()


def crop(pixels, i: int) -> np.ndarray:
    """The ``i``-th 640 × 512 RGB crop of ``pixels`` (:func:`sample_pixels`), a different piece of tissue per ``i``."""
    y, x = 320 + (i * 160) % 1920, 768 + (i * 64) % 512
    return np.ascontiguousarray(pixels[y : y + 640, x : x + 512, :3])
