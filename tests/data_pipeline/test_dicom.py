"""DICOM WSI (VL Whole Slide Microscopy) through data_tools: info, pixels where the frame positions say,
dense and tiled builds, and one-line errors for bad DICOM.

The fixture ``tests/data/dicom-wsi`` (written by ``tests/data/make_dicom_wsi.py`` from the CC0 sample
slide) has a column-by-column TILED_SPARSE JPEG level, a TILED_SPARSE JPEG 2000 level with two frames
absent, and a TILED_FULL JPEG level.
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("wsidicom", reason="the dicom extra is not installed: pip install 'histojax[dicom]'")

from data_tools.__main__ import main as data_tools_main  # noqa: E402
from data_tools.bundle import build_bundle, load_bundle  # noqa: E402
from data_tools.errors import SlideError  # noqa: E402
from data_tools.slide_files.open import open_slide  # noqa: E402

DATA = Path(__file__).parents[1] / "data"
FIXTURE = DATA / "dicom-wsi"
TILE = 128


@pytest.fixture(scope="module")
def reference():
    """The pixels each fixture level was encoded from, and the level-0 µm/px."""
    spec = importlib.util.spec_from_file_location("make_dicom_wsi", DATA / "make_dicom_wsi.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.reference_levels()


def test_fixture_is_small():
    assert sum(f.stat().st_size for f in FIXTURE.iterdir()) < 1_000_000


@pytest.mark.parametrize("path", [FIXTURE, FIXTURE / "level1.dcm"], ids=["folder", "one-file"])
def test_info_lists_the_pyramid(path, capsys):
    assert data_tools_main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert "format: dicom-wsi" in out and "mpp: 1.996 µm/px" in out
    assert "level 0: 512×640 px, downsample 1.000, tiles 128×128, JPEG" in out
    assert "level 1: 256×320 px, downsample 2.000, tiles 128×128, JPEG2000" in out
    assert "level 2: 128×160 px, downsample 4.000, tiles 128×128, JPEG" in out


def test_every_frame_where_its_position_says(reference):
    """Each 128-px tile of each level is close to the pixels it was encoded from (lossy codecs), so a frame
    put in row-major order when stored column by column, or a shifted sparse frame, fails; absent frames
    of the sparse level are white."""
    levels, mpp = reference
    with open_slide(FIXTURE) as reader:
        assert reader.mpp == pytest.approx(mpp, rel=1e-3)
        for k, ref in enumerate(levels):
            got = reader.read_level(k)
            assert got.shape == ref.shape and got.dtype == np.uint8
            for ty in range(0, ref.shape[0], TILE):
                for tx in range(0, ref.shape[1], TILE):
                    err = np.abs(
                        got[ty : ty + TILE, tx : tx + TILE].astype(int) - ref[ty : ty + TILE, tx : tx + TILE]
                    ).mean()
                    assert err < 8, (k, tx, ty, err)
        level1 = reader.read_level(1)
        assert (level1[:TILE, :TILE] == 255).all() and (level1[2 * TILE :, TILE:] == 255).all()
        assert not (level1[:TILE, TILE:] == 255).all()


def test_region_outside_is_white_and_matches_level():
    with open_slide(FIXTURE) as reader:
        whole = reader.read_level(0)
        region = reader.read_region(0, 400, 500, 200, 200)
        np.testing.assert_array_equal(region[:140, :112], whole[500:, 400:])
        assert (region[140:] == 255).all() and (region[:, 112:] == 255).all()


def test_build_dense_and_tiled(tmp_path, reference):
    """A DICOM folder builds dense and tiled bundles that agree, with the annotated tumour."""
    ann = tmp_path / "tumour.geojson"
    ann.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {"classification": {"name": "Tumor"}},
                        "geometry": {
                            "type": "Polygon",
                            "coordinates": [[[100, 100], [300, 100], [300, 260], [100, 260], [100, 100]]],
                        },
                    }
                ],
            }
        )
    )
    kw = dict(annotations_path=ann, tile_size=64, level_sets=(3,), progress=False)
    dense = load_bundle(build_bundle(FIXTURE, tmp_path / "dense", **kw))
    tiled = load_bundle(build_bundle(FIXTURE, tmp_path / "tiled", storage="tiled", share_background=False, **kw))
    assert dense.metadata["source"]["format"] == "dicom-wsi" and tiled.storage == "tiled"
    for k in range(len(dense.pixels)):
        np.testing.assert_array_equal(np.asarray(tiled.pixels[k]), dense.pixels[k])
    assert np.abs(dense.pixels[0].astype(int) - reference[0][0]).mean() < 8
    assert dense.tumour[0].sum() == 200 * 160


def test_non_wsi_dicom_is_one_line_error(tmp_path, capsys):
    from pydicom.dataset import Dataset, FileMetaDataset

    ds = Dataset()
    ds.file_meta = FileMetaDataset()
    ds.file_meta.MediaStorageSOPClassUID = ds.SOPClassUID = "1.2.840.10008.5.1.4.1.1.2"  # CT Image Storage
    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID = "1.2.3.4"
    ds.file_meta.TransferSyntaxUID = "1.2.840.10008.1.2.1"
    ds.Modality, ds.SeriesInstanceUID = "CT", "1.2.3"
    folder = tmp_path / "ct"
    folder.mkdir()
    ds.save_as(folder / "ct.dcm", enforce_file_format=True)
    with pytest.raises(SlideError, match="ct.dcm: a DICOM file but not a whole-slide image"):
        open_slide(folder / "ct.dcm")
    assert data_tools_main(["info", str(folder)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {folder}: ") and "VL Whole Slide Microscopy" in err and err.count("\n") == 1


@pytest.mark.parametrize("keep", [2000, 60_000], ids=["header", "frames"])
def test_truncated_dicom_is_one_line_error_and_nothing_written(tmp_path, keep, capsys):
    folder = tmp_path / "cut"
    folder.mkdir()
    for f in FIXTURE.iterdir():
        data = f.read_bytes()
        (folder / f.name).write_bytes(data[:keep] if f.name == "level0.dcm" else data)
    out = tmp_path / "bundle"
    assert data_tools_main(["build", str(folder), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {folder}") and err.count("\n") == 1, err
    assert not out.exists() and [p.name for p in tmp_path.iterdir()] == ["cut"]


def test_missing_wsidicom_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "wsidicom", None)
    with pytest.raises(SlideError, match=r"pip install 'histojax\[dicom\]'"):
        open_slide(FIXTURE)
