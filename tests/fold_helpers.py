"""The small folded dataset of the fold tests (``tests/data_pipeline/test_folds.py``, ``tests/reading/test_all_folds.py``), built once here."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tifffile

from data_tools.__main__ import main as data_main
from histojax.sample import SAMPLE_SLIDE

SLIDES = [("t0", 1), ("t1", 1), ("t2", 1), ("t3", 1), ("n0", 0), ("n1", 0), ("n2", 0)]
"""The slides (name, label): 4 tumour, 3 normal; t0 and t1 are one patient (``PT``)."""


def build_folded(root: Path, folds: int = 2, encoder: str | None = None) -> Path:
    """A 7-slide dataset (:data:`SLIDES`: 320 × 256 px crops of the sample slide at 0.5 µm/px, a label table with a
    patient column) built by ``histojax dataset`` into ``root/ds`` with ``--folds folds``, 3 levels of 64-px views
    and ``--encoder encoder`` when given; returns ``root/ds``."""
    with tifffile.TiffFile(SAMPLE_SLIDE) as tif:
        pixels = tif.pages[0].asarray()
    slides = root / "S"
    slides.mkdir()
    rows = ["slide,label,patient"]
    for i, (name, label) in enumerate(SLIDES):
        y, x = 320 + i * 160, 768 + (i * 64) % 512
        tifffile.imwrite(
            slides / f"{name}.tif",
            np.ascontiguousarray(pixels[y : y + 256, x : x + 320, :3]),
            photometric="rgb",
            resolution=(2e4, 2e4),
            resolutionunit="CENTIMETER",
        )
        rows.append(f"{name},{label},{'PT' if name in ('t0', 't1') else name.upper()}")
    (root / "labels.csv").write_text("\n".join(rows) + "\n")
    out = root / "ds"
    assert (
        data_main(
            [
                "dataset",
                str(slides),
                "--out",
                str(out),
                "--labels",
                str(root / "labels.csv"),
                "--levels",
                "3",
                "--tile-size",
                "64",
                "--quiet",
                "--folds",
                str(folds),
                *(["--encoder", encoder] if encoder else []),
            ]
        )
        == 0
    )
    return out
