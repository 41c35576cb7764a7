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
