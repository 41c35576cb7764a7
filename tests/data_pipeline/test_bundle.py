"""Tests for data_tools.bundle: building, checking and loading slide bundles (atomic writes, checksums)."""

from __future__ import annotations

import hashlib
import json
import math
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

import data_tools.masks
from data_tools.annotations import load_annotations
from data_tools.bundle import (
    FORMAT_VERSION,
    METADATA,
    build_bundle,
    bundle_downsamples,
    default_magnification_range,
    level_downsamples,
    load_bundle,
    read_metadata,
)
from data_tools.errors import AnnotationError, BundleError, SlideError

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"
TARGET = ROOT / "histojax" / "data" / "CMU-1-Small-Region.target.xml"
KIDNEY = ROOT / "tests" / "data" / "kidney-48-5_IHC.tif"
BROKEN = ROOT / "tests" / "data" / "broken.svs"
FAR_ANNOTATION = ROOT / "tests" / "data" / "annotations" / "tumor_076.xml"


def _leftovers(parent: Path, name: str) -> list[Path]:
    """Hidden temporary / old folders a build of ``parent/name`` may leave behind."""
    return sorted(parent.glob(f".{name}.*"))


def _copy(bundle: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(bundle, dst)
    return dst


@pytest.fixture(scope="module")
def svs_bundle(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("svs") / "bundle"
    return build_bundle(SVS, out, annotations_path=TARGET, level_sets=(3, 5, 7), tile_size=128, progress=False)


@pytest.fixture(scope="module")
def kidney_bundle(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("kidney") / "bundle"
    return build_bundle(KIDNEY, out, level_sets=(3,), progress=False)


# ---------------------------------------------------------------------------
# SVS bundle with the target annotation


def test_svs_metadata(svs_bundle):
    meta = read_metadata(svs_bundle)
    assert meta["format_version"] == FORMAT_VERSION
    assert meta["source"]["file"] == SVS.name
    assert meta["source"]["sha256"] == hashlib.sha256(SVS.read_bytes()).hexdigest()
    assert (meta["source"]["width"], meta["source"]["height"]) == (2220, 2967)
    assert meta["source"]["mpp"] == pytest.approx(0.499)
    assert meta["tile_size"] == 128
    assert meta["label_map"] == {}
    assert meta["level_sets"] == [3, 5, 7]
    assert meta["magnification_range"] == 16

    expected = sorted({16 ** (k / n) for n in (2, 4, 6) for k in range(n + 1)})
    expected = [d for i, d in enumerate(expected) if i == 0 or not math.isclose(d, expected[i - 1])]
    downsamples = [lv["downsample"] for lv in meta["levels"]]
    assert len(downsamples) == 9
    assert downsamples == pytest.approx(expected)
    assert downsamples[0] == 1 and downsamples[-1] == pytest.approx(16)
    for lv in meta["levels"]:
        assert lv["mpp"] == pytest.approx(0.499 * lv["downsample"])
        assert lv["width"] >= 128 and lv["height"] >= 128

    npy = sorted(p.name for p in svs_bundle.glob("*.npy"))
    assert len(npy) == 2 * 9 + 1
    assert set(npy) <= set(meta["checksums"])
    for name in npy:
        assert meta["checksums"][name] == hashlib.sha256((svs_bundle / name).read_bytes()).hexdigest()


def test_svs_load_shapes_and_dtypes(svs_bundle):
    b = load_bundle(svs_bundle)
    assert len(b.pixels) == len(b.tumour) == len(b.metadata["levels"]) == 9
    assert b.tile_size == 128
    for lv, px, tu in zip(b.metadata["levels"], b.pixels, b.tumour):
        assert px.shape == (lv["height"], lv["width"], 3)
        assert px.dtype == np.uint8
        assert tu.shape == (lv["height"], lv["width"])
        assert set(np.unique(tu)) <= {0, 1}
        assert int(tu.sum()) == lv["tumour_pixels"]
    coarsest = b.metadata["levels"][-1]
    assert b.tissue.shape == (coarsest["height"], coarsest["width"])
    assert b.tissue.dtype == bool
    assert 0.15 < b.tissue.mean() < 0.85
    # the finest level is the slide, unpadded
    assert b.pixels[0].shape == (2967, 2220, 3)


def test_svs_tumour_counts_match_annotation_area(svs_bundle):
    area = load_annotations(TARGET).tumour.area
    assert area > 0
    b = load_bundle(svs_bundle)
    assert abs(int(b.tumour[0].sum()) - area) <= 0.01 * area
    for d, tu in zip(b.downsamples[1:], b.tumour[1:]):
        assert abs(int(tu.sum()) * d * d - area) <= 0.05 * area, d
    assert b.metadata["annotations"]["tumour_area_px"] == pytest.approx(area)


def test_no_pickles(svs_bundle):
    for f in svs_bundle.glob("*.npy"):
        np.load(f, allow_pickle=False)


# ---------------------------------------------------------------------------
# level arithmetic


def test_level_downsamples():
    assert level_downsamples(3, 16) == pytest.approx([16, 4, 1])
    assert level_downsamples(5, 16) == pytest.approx([16, 8, 4, 2, 1])
    for n in (2, 3, 5, 7):
        ds = level_downsamples(n, 16)
        assert len(ds) == n
        assert ds[0] == pytest.approx(16) and ds[-1] == 1
        assert all(a > b for a, b in zip(ds, ds[1:]))
    with pytest.raises(ValueError):
        level_downsamples(1, 16)


def test_bundle_downsamples_dedupes():
    assert bundle_downsamples((3, 5), 16) == pytest.approx([1, 2, 4, 8, 16])
    assert bundle_downsamples((3, 3, 5, 5), 16) == pytest.approx([1, 2, 4, 8, 16])
    assert len(bundle_downsamples((3, 5, 7), 16)) == 9
    assert bundle_downsamples((3,), 4) == pytest.approx([1, 2, 4])


def test_default_magnification_range():
    assert default_magnification_range(2220, 2967, 128) == 16
    assert default_magnification_range(1493, 901, 128) == 4
    assert default_magnification_range(100, 100, 128) == 1


# ---------------------------------------------------------------------------
# atomic writes and overwrite


def test_crash_leaves_nothing(tmp_path, monkeypatch):
    real = data_tools.masks.rasterize
    calls = {"n": 0}

    def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise RuntimeError("simulated crash")
        return real(*args, **kwargs)

    monkeypatch.setattr(data_tools.masks, "rasterize", flaky)
    out = tmp_path / "bundle"
    with pytest.raises(RuntimeError, match="simulated crash"):
        build_bundle(SVS, out, annotations_path=TARGET, level_sets=(3, 5), progress=False)
    assert calls["n"] == 3
    assert not out.exists()
    assert _leftovers(tmp_path, "bundle") == []
    assert list(tmp_path.iterdir()) == []


def test_existing_out_dir_needs_overwrite(tmp_path):
    out = tmp_path / "bundle"
    out.mkdir()
    (out / "keep.txt").write_text("not a bundle")
    with pytest.raises(BundleError, match="overwrite") as info:
        build_bundle(KIDNEY, out, level_sets=(3,), progress=False)
    assert str(out) in str(info.value)
    assert (out / "keep.txt").read_text() == "not a bundle"

    # a folder of someone's files is not a bundle: --overwrite refuses it too, and deletes nothing
    with pytest.raises(BundleError, match="not a histojax bundle"):
        build_bundle(KIDNEY, out, level_sets=(3,), progress=False, overwrite=True)
    assert (out / "keep.txt").read_text() == "not a bundle"

    (out / "keep.txt").unlink()  # an empty folder may be filled
    build_bundle(KIDNEY, out, level_sets=(3,), progress=False, overwrite=True)
    b = load_bundle(out)
    assert len(b.pixels) == 3
    build_bundle(KIDNEY, out, level_sets=(3, 5), progress=False, overwrite=True)  # a bundle may be replaced
    assert len(load_bundle(out).pixels) == 5
    assert _leftovers(tmp_path, "bundle") == []


def test_overwrite_refuses_a_regular_file(tmp_path):
    out = tmp_path / "bundle"
    out.write_text("precious")
    with pytest.raises(BundleError, match="is a file"):
        build_bundle(KIDNEY, out, level_sets=(3,), progress=False, overwrite=True)
    assert out.read_text() == "precious"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bundle"]  # no .bundle.old-* copy left behind


# ---------------------------------------------------------------------------
# corruption and bad metadata


def test_flipped_byte_is_detected(svs_bundle, tmp_path):
    copy = _copy(svs_bundle, tmp_path)
    victim = copy / "pixels_08.npy"
    data = bytearray(victim.read_bytes())
    data[-1] ^= 0xFF  # in the pixel data, so the header stays readable
    victim.write_bytes(bytes(data))
    with pytest.raises(BundleError, match="rebuild") as info:
        load_bundle(copy)
    assert "pixels_08.npy" in str(info.value)
    b = load_bundle(copy, verify=False)
    assert len(b.pixels) == 9
    # the original is untouched
    load_bundle(svs_bundle, levels=[8])


def test_bad_metadata_json(kidney_bundle, tmp_path):
    copy = _copy(kidney_bundle, tmp_path)
    (copy / METADATA).write_text("{not json")
    with pytest.raises(BundleError, match="metadata"):
        load_bundle(copy)


@pytest.mark.parametrize("text", ["[]", "null", '"a string"', "42"])
def test_metadata_not_an_object(kidney_bundle, tmp_path, text):
    copy = _copy(kidney_bundle, tmp_path)
    (copy / METADATA).write_text(text)
    with pytest.raises(BundleError):
        load_bundle(copy)


def test_other_format_version(kidney_bundle, tmp_path):
    copy = _copy(kidney_bundle, tmp_path)
    meta = json.loads((copy / METADATA).read_text())
    meta["format_version"] = 999
    (copy / METADATA).write_text(json.dumps(meta))
    with pytest.raises(BundleError, match="999") as info:
        load_bundle(copy)
    assert "version" in str(info.value)


def test_missing_metadata(kidney_bundle, tmp_path):
    copy = _copy(kidney_bundle, tmp_path)
    (copy / METADATA).unlink()
    with pytest.raises(BundleError, match="not a slide bundle"):
        load_bundle(copy)
    with pytest.raises(BundleError, match="not a slide bundle"):
        load_bundle(tmp_path / "nowhere")


def test_missing_array(kidney_bundle, tmp_path):
    copy = _copy(kidney_bundle, tmp_path)
    (copy / "tumour_01.npy").unlink()
    with pytest.raises(BundleError, match="tumour_01.npy"):
        load_bundle(copy)


# ---------------------------------------------------------------------------
# single-level stripped TIFF


def test_kidney_levels_by_downsampling(kidney_bundle):
    b = load_bundle(kidney_bundle)
    levels = b.metadata["levels"]
    assert len(levels) == 3
    assert b.downsamples == pytest.approx([1, 2, 4])
    assert (levels[0]["content_width"], levels[0]["content_height"]) == (1493, 901)
    for fine, coarse in zip(levels, levels[1:]):
        assert abs(coarse["content_width"] - fine["content_width"] / 2) <= 1
        assert abs(coarse["content_height"] - fine["content_height"] / 2) <= 1
    assert b.metadata["annotations"] is None
    assert all(not t.any() for t in b.tumour)

    finest = b.pixels[0].astype(np.float64)
    for lv, px in zip(levels[1:], b.pixels[1:]):
        d = lv["downsample"]
        assert d == int(d)
        d = int(d)
        h, w = lv["content_height"], lv["content_width"]
        block = finest[: h * d, : w * d].reshape(h, d, w, d, 3).mean(axis=(1, 3))
        assert np.abs(block - px[:h, :w]).mean() < 3


# ---------------------------------------------------------------------------
# bad input leaves no output


def test_broken_slide(tmp_path):
    out = tmp_path / "bundle"
    with pytest.raises(SlideError, match="broken.svs"):
        build_bundle(BROKEN, out, progress=False)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_annotation_outside_slide(tmp_path):
    out = tmp_path / "bundle"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "extend beyond the slide", self-intersection repairs
        with pytest.raises(AnnotationError, match="outside the slide") as info:
            build_bundle(SVS, out, annotations_path=FAR_ANNOTATION, level_sets=(3,), progress=False)
    assert FAR_ANNOTATION.name in str(info.value)
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("tile_size", [0, 4])
def test_tiny_tile_size(tmp_path, tile_size):
    with pytest.raises(BundleError, match="tile size"):
        build_bundle(KIDNEY, tmp_path / "bundle", tile_size=tile_size, progress=False)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("magnification_range", [0.5, -4.0])
def test_bad_magnification_range(tmp_path, magnification_range):
    with pytest.raises(BundleError, match="magnification"):
        build_bundle(KIDNEY, tmp_path / "bundle", magnification_range=magnification_range, progress=False)
    assert list(tmp_path.iterdir()) == []
