"""``histojax dataset --folds K`` on a finished dataset: the folds depend on the labels and patients alone, so
``dataset.json`` is written again with them and no bundle is rebuilt; a refused rerun names what differs in
plain words."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from data_tools.__main__ import main as data_main
from histojax.sample import SAMPLE_SLIDE


@pytest.fixture(scope="module")
def unfolded(tmp_path_factory):
    """A finished 6-slide dataset built without ``--folds`` (3 tumour, 3 normal, 64-px views, one level) and the
    command that built it."""
    root = tmp_path_factory.mktemp("unfolded")
    with tifffile.TiffFile(SAMPLE_SLIDE) as tif:
        pixels = tif.pages[0].asarray()
    slides = root / "S"
    slides.mkdir()
    rows = ["slide,label"]
    for i, (name, label) in enumerate([("t0", 1), ("t1", 1), ("t2", 1), ("n0", 0), ("n1", 0), ("n2", 0)]):
        y, x = 320 + i * 160, 768 + (i * 64) % 512
        tifffile.imwrite(
            slides / f"{name}.tif",
            np.ascontiguousarray(pixels[y : y + 256, x : x + 320, :3]),
            photometric="rgb",
            resolution=(2e4, 2e4),
            resolutionunit="CENTIMETER",
        )
        rows.append(f"{name},{label}")
    (root / "labels.csv").write_text("\n".join(rows) + "\n")
    command = [
        "dataset",
        str(slides),
        "--out",
        str(root / "ds"),
        "--labels",
        str(root / "labels.csv"),
        "--levels",
        "3",
        "--tile-size",
        "64",
        "--quiet",
    ]
    assert data_main(command) == 0
    return root / "ds", command


def _bundle_times(ds: Path) -> dict:
    return {str(p.relative_to(ds)): p.stat().st_mtime_ns for p in sorted((ds / "bundles").rglob("*")) if p.is_file()}


def test_adding_folds_to_a_finished_dataset_rewrites_dataset_json_without_rebuilding(unfolded, capsys):
    ds, command = unfolded
    before = _bundle_times(ds)
    assert "folds" not in json.loads((ds / "dataset.json").read_text())
    assert data_main([*command, "--folds", "3"]) == 0  # no --restart needed: only the folds are new
    out = capsys.readouterr().out
    assert "0 built, 6 already done" in out and "folds are new" in out, out
    folds = json.loads((ds / "dataset.json").read_text())["folds"]
    assert folds["k"] == 3 and sum(len(f) for f in folds["lists"]) == 6
    assert _bundle_times(ds) == before  # no bundle written again


def test_a_rerun_with_other_options_names_them_in_plain_words(unfolded, capsys):
    ds, command = unfolded
    before = (ds / "plan.json").read_bytes()
    assert data_main([*command[:-2], "32", "--quiet"]) == 2  # --tile-size 32
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and len(err.splitlines()) == 1, err
    assert "started with other options" in err and "(options ['tile_size'])" in err and "a different" not in err, err
    assert (ds / "plan.json").read_bytes() == before
