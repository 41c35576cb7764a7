"""The OpenSlide 4 backend (data_tools.slide_files.openslide): the same levels and pixels as the native readers on the
fixtures here (Aperio SVS, tiled pyramidal TIFF, DICOM WSI), a MIRAX slide written from OpenSlide's description of
the format (tests/mirax_fixture.py), one-line errors for bad files, the missing-extra line, and ``--reader
openslide`` through ``info`` / ``build`` / ``dataset``.

Pixel tolerance: none. OpenSlide 4 and tifffile / wsidicom decode the same JPEG / JPEG 2000 tiles to the same bytes
here (both through libjpeg-turbo and OpenJPEG), so every comparison is exact; a level whose downsample is not a whole
number (703 px → 352 px: 1.997) is read from a corner OpenSlide maps to a whole level pixel, else OpenSlide
interpolates (up to 26 grey levels off before that was done)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tifffile

from data_tools.errors import SlideError
from data_tools.slide_files.open import open_slide

openslide = pytest.importorskip("openslide", reason="the optional extra histojax[openslide] is not installed")

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"
DICOM = ROOT / "tests" / "data" / "dicom-wsi"
BROKEN = ROOT / "tests" / "data" / "broken.svs"


def _gradient(h: int, w: int) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w]
    return np.stack([(xx * 0.3) % 255, (yy * 0.5) % 255, ((xx + yy) * 0.2) % 255], -1).astype(np.uint8)


def _tiff(path: Path, rgb: np.ndarray, compression=None) -> Path:
    """A tiled pyramid as OpenSlide's generic TIFF reads it: levels as top-level IFDs (reduced-resolution after
    the first), each half the previous (odd sizes round up, so the downsamples are not whole numbers)."""
    levels = [rgb]
    while len(levels) < 3:
        levels.append(np.ascontiguousarray(levels[-1][::2, ::2]))
    with tifffile.TiffWriter(path) as tif:
        for k, lv in enumerate(levels):
            tif.write(
                lv,
                tile=(128, 128),
                photometric="rgb",
                compression=compression,
                subfiletype=1 if k else 0,
                resolution=(2e4 / 2**k, 2e4 / 2**k),
                resolutionunit="CENTIMETER",
                metadata=None,
            )
    return path


@pytest.fixture(scope="module")
def fixtures(tmp_path_factory):
    d = tmp_path_factory.mktemp("openslide")
    return {
        "svs": SVS,
        "dicom": DICOM,
        "tiff-deflate": _tiff(d / "deflate.tif", _gradient(601, 703), "zlib"),
        "tiff-jpeg": _tiff(d / "jpeg.tif", _gradient(601, 703), "jpeg"),
    }


@pytest.mark.parametrize("name", ["svs", "tiff-deflate", "tiff-jpeg", "dicom"])
def test_openslide_reports_the_native_levels_and_pixels(fixtures, name):
    path = fixtures[name]
    with open_slide(path, "native") as a, open_slide(path, "openslide") as b:
        assert b.format.startswith("openslide-") and not a.format.startswith("openslide")
        assert [(lv.width, lv.height) for lv in b.levels] == [(lv.width, lv.height) for lv in a.levels]
        np.testing.assert_allclose([lv.downsample for lv in b.levels], [lv.downsample for lv in a.levels], rtol=1e-9)
        assert b.mpp == pytest.approx(a.mpp, rel=1e-6)
        for k, lv in enumerate(a.levels):
            np.testing.assert_array_equal(b.read_level(k), a.read_level(k), err_msg=f"{name} level {k}")
            for x, y, w, h in ((37, 53, 101, 77), (lv.width - 50, lv.height - 40, 90, 90), (-10, -10, 30, 30)):
                np.testing.assert_array_equal(
                    b.read_region(k, x, y, w, h),
                    a.read_region(k, x, y, w, h),
                    err_msg=f"{name} level {k} region {(x, y, w, h)}",
                )


def test_non_whole_downsamples_are_read_without_interpolation(fixtures):
    """Was (OpenSlide asked at ``round(x × downsample)``): up to 26 grey levels off on level 2 (downsample 3.987)."""
    with open_slide(fixtures["tiff-deflate"], "openslide") as b:
        assert not float(b.levels[2].downsample).is_integer()
        rgb = _gradient(601, 703)[::4, ::4]
        np.testing.assert_array_equal(b.read_region(2, 126, 111, 40, 30), rgb[111:141, 126:166])


def test_associated_images_and_mpp_as_openslide_reports_them():
    with open_slide(SVS, "openslide") as b:
        slide = openslide.OpenSlide(str(SVS))
        assert b.mpp == float(slide.properties["openslide.mpp-x"])
        assert b.associated == {n: im.size for n, im in slide.associated_images.items()}
        assert {"label", "macro", "thumbnail"} <= set(b.associated)


def test_broken_files_get_one_line(tmp_path):
    for path, match in ((BROKEN, "format not recognised by OpenSlide"), (tmp_path / "missing.mrxs", "file not found")):
        with pytest.raises(SlideError, match=match) as e:
            open_slide(path, "openslide")
        assert str(path) in str(e.value) and "\n" not in str(e.value)
    bad = tmp_path / "bad.mrxs"  # a MIRAX name with no MIRAX in it: read through OpenSlide (auto), refused in a line
    bad.write_text("not a slide")
    with pytest.raises(SlideError, match="bad.mrxs: its data folder bad/ is missing"):
        open_slide(bad)


def test_a_truncated_tiff_through_openslide_is_one_line(fixtures, tmp_path):
    data = Path(fixtures["tiff-jpeg"]).read_bytes()
    cut = tmp_path / "cut.tif"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(SlideError) as e:
        with open_slide(cut, "openslide") as b:
            b.read_level(0)
    assert "cut.tif" in str(e.value) and "\n" not in str(e.value)


def test_without_the_extra_one_line_names_it(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "openslide", None)  # import openslide raises ImportError
    (tmp_path / "s.mrxs").write_text("x")
    for path, reader in ((tmp_path / "s.mrxs", "auto"), (SVS, "openslide")):
        with pytest.raises(SlideError, match=r"pip install 'histojax\[openslide\]'") as e:
            open_slide(path, reader)
        assert "\n" not in str(e.value)


def _cli(*args):
    return subprocess.run(
        [sys.executable, "-m", "data_tools", *map(str, args)], capture_output=True, text=True, cwd=ROOT, timeout=300
    )


def test_info_and_build_with_reader_openslide(fixtures, tmp_path):
    proc = _cli("info", SVS, "--reader", "openslide")
    assert proc.returncode == 0, proc.stderr
    assert "format: openslide-aperio" in proc.stdout and "associated images: label" in proc.stdout
    proc = _cli("info", BROKEN, "--reader", "openslide")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1 and "broken.svs" in proc.stderr
    for reader in ("native", "openslide"):
        proc = _cli(
            "build",
            fixtures["tiff-jpeg"],
            "--out",
            tmp_path / reader,
            "--levels",
            "3",
            "--storage",
            "tiled",
            "--quiet",
            "--reader",
            reader,
        )
        assert proc.returncode == 0, proc.stderr
    meta = {r: json.loads((tmp_path / r / "metadata.json").read_text()) for r in ("native", "openslide")}
    assert meta["openslide"]["source"]["format"] == "openslide-generic-tiff"
    arrays = sorted(p.name for p in (tmp_path / "native").glob("*.npy"))
    assert len(arrays) >= 3
    for f in arrays:  # the same pixels, byte for byte
        np.testing.assert_array_equal(np.load(tmp_path / "openslide" / f), np.load(tmp_path / "native" / f), err_msg=f)


def test_dataset_with_reader_openslide_records_it(fixtures, tmp_path):
    slides = tmp_path / "S"
    slides.mkdir()
    for k in range(2):
        (slides / f"s{k}.tif").write_bytes(Path(fixtures["tiff-jpeg"]).read_bytes())
    proc = _cli(
        "dataset",
        slides,
        "--out",
        tmp_path / "o",
        "--levels",
        "3",
        "--quiet",
        "--test-fraction",
        "0",
        "--reader",
        "openslide",
    )
    assert proc.returncode == 0, proc.stderr
    ds = json.loads((tmp_path / "o" / "dataset.json").read_text())
    assert ds["options"]["reader"] == "openslide"
    assert {s["format"] for s in ds["slides"]} == {"openslide-generic-tiff"}


# ------------------------------------------------------------------ MIRAX: a fixture written from OpenSlide's format
@pytest.fixture(scope="module")
def mirax_slide(tmp_path_factory):
    """A 512 × 256 px MIRAX slide of real pixels (a crop of the sample slide), two levels, PNG images."""
    from mirax_fixture import mirax

    with tifffile.TiffFile(SVS) as tif:
        rgb = np.ascontiguousarray(tif.pages[0].asarray()[400:656, 800:1312, :3])
    return mirax(tmp_path_factory.mktemp("mirax") / "S" / "slide.mrxs", rgb)


def test_a_mirax_slide_is_read_through_openslide(mirax_slide):
    path, levels = mirax_slide
    with open_slide(path) as b:  # auto: .mrxs goes to OpenSlide
        assert b.format == "openslide-mirax" and b.mpp == 0.25
        assert [(lv.width, lv.height, lv.downsample) for lv in b.levels] == [(512, 256, 1.0), (256, 128, 2.0)]
        for k, (img, _) in enumerate(levels):  # PNG images: the pixels written, exactly
            np.testing.assert_array_equal(b.read_level(k), img)
        np.testing.assert_array_equal(b.read_region(0, 100, 60, 200, 100), levels[0][0][60:160, 100:300])
    with pytest.raises(SlideError):
        open_slide(path, "native")  # the native readers do not read MIRAX


def test_a_mirax_folder_becomes_a_dataset_and_a_bundle(mirax_slide, tmp_path):
    from data_tools.datasets.discover import discover

    path, levels = mirax_slide
    skipped = []
    entries = discover(path.parent, skipped=skipped)
    assert [(e.name, e.path) for e in entries] == [("slide", path)]
    assert skipped == []  # its data folder (Slidedat.ini, Index.dat, Data0000.dat) is part of the slide
    proc = _cli("build", path, "--out", tmp_path / "b", "--levels", "3", "--tile-size", "64", "--quiet")
    assert proc.returncode == 0, proc.stderr
    meta = json.loads((tmp_path / "b" / "metadata.json").read_text())
    assert meta["source"]["format"] == "openslide-mirax" and meta["source"]["width"] == 512


def test_a_broken_mirax_is_one_line(mirax_slide, tmp_path):
    import shutil

    path, _ = mirax_slide
    bad = tmp_path / "bad.mrxs"
    shutil.copytree(path.with_suffix(""), tmp_path / "bad")
    bad.write_bytes(b"")
    index = tmp_path / "bad" / "Index.dat"
    index.write_bytes(index.read_bytes()[:40])  # truncated: the level pages are gone
    with pytest.raises(SlideError, match=r"bad\.mrxs: format not recognised or file corrupt \(OpenSlide: ") as e:
        open_slide(bad)
    assert "\n" not in str(e.value)
