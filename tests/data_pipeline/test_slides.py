"""Tests for data_tools.slide_files.tiff: reading SVS / pyramidal TIFF / OME-TIFF as 8-bit RGB."""

from __future__ import annotations

from pathlib import Path

import imagecodecs
import numpy as np
import pytest
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

from data_tools.errors import SlideError
from data_tools.slide_files.base import MAX_DECODE_BYTES, LevelInfo, SlideReader, describe
from data_tools.slide_files.open import open_slide
from data_tools.slide_files.tiff import TiffSlideReader

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"
KIDNEY = ROOT / "tests" / "data" / "kidney-48-5_IHC.tif"
BROKEN = ROOT / "tests" / "data" / "broken.svs"


# ---------------------------------------------------------------------------
# helpers


def _image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """Smooth RGB test image with some texture (compresses sensibly with JPEG)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    r = 128 + 100 * np.sin(xx / 37.0)
    g = 128 + 100 * np.cos(yy / 23.0)
    b = (xx + yy) % 256
    img = np.stack([r, g, b], axis=-1) + rng.normal(0, 4, (height, width, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def _write_pyramid(path: Path, base: np.ndarray, compression: str, ome: bool = False, **meta) -> None:
    """3-level tiled pyramid (1, 1/2, 1/4) stored as SubIFDs, as in tifffile's docs."""
    options = dict(tile=(128, 128), compression=compression, photometric="rgb")
    kwargs = {"metadata": {"axes": "YXS", **meta}} if ome else {}
    with tifffile.TiffWriter(path, ome=ome) as tif:
        tif.write(base, subifds=2, **options, **kwargs)
        tif.write(base[::2, ::2], subfiletype=1, **options)
        tif.write(base[::4, ::4], subfiletype=1, **options)


def _padded_slice(full: np.ndarray, x: int, y: int, w: int, h: int) -> np.ndarray:
    """full[y:y+h, x:x+w] with everything outside ``full`` white."""
    out = np.full((h, w, 3), 255, np.uint8)
    H, W = full.shape[:2]
    x0, y0, x1, y1 = max(x, 0), max(y, 0), min(x + w, W), min(y + h, H)
    if x0 < x1 and y0 < y1:
        out[y0 - y : y1 - y, x0 - x : x1 - x] = full[y0:y1, x0:x1]
    return out


@pytest.fixture(scope="module")
def svs_level0() -> np.ndarray:
    with open_slide(SVS) as r:
        return r.read_level(0)


@pytest.fixture(scope="module")
def zlib_pyramid(tmp_path_factory) -> tuple[Path, np.ndarray]:
    base = _image(600, 520, seed=1)
    path = tmp_path_factory.mktemp("pyr") / "zlib_pyramid.tif"
    _write_pyramid(path, base, "zlib")
    return path, base


# ---------------------------------------------------------------------------
# Aperio SVS fixture


def test_svs_metadata():
    with open_slide(SVS) as r:
        assert isinstance(r, TiffSlideReader) and isinstance(r, SlideReader)  # the TIFF reader, one subclass
        assert r.path == str(SVS)
        assert r.format == "aperio-svs"
        assert len(r.levels) == 1  # thumbnail / label / macro are not levels
        assert r.levels[0] == LevelInfo(2220, 2967, 1.0, (240, 240), "JPEG")
        assert r.dimensions == (2220, 2967)
        assert r.mpp == pytest.approx(0.499)
        text = describe(r)
    assert "CMU-1-Small-Region.svs" in text
    assert "aperio-svs" in text and "0.499" in text
    assert "2220×2967" in text and "240×240" in text and "JPEG" in text


def test_svs_read_level_and_region(svs_level0):
    img = svs_level0
    assert img.shape == (2967, 2220, 3) and img.dtype == np.uint8
    assert img.std() > 10
    with open_slide(SVS) as r:
        # crosses tile boundaries (tiles are 240 px)
        region = r.read_region(0, 200, 470, 333, 290)
        assert np.array_equal(region, img[470:760, 200:533])
        # the last, partial tiles
        region = r.read_region(0, 2000, 2800, 220, 167)
        assert np.array_equal(region, img[2800:2967, 2000:2220])


def test_svs_region_past_edge_is_white(svs_level0):
    with open_slide(SVS) as r:
        region = r.read_region(0, 2100, 2900, 200, 100)
    assert region.shape == (100, 200, 3)
    assert np.array_equal(region[:67, :120], svs_level0[2900:, 2100:])
    assert (region[67:] == 255).all() and (region[:, 120:] == 255).all()
    with open_slide(SVS) as r:
        assert (r.read_region(0, 5000, 5000, 10, 10) == 255).all()
        assert np.array_equal(r.read_region(0, -5, -7, 20, 20), _padded_slice(svs_level0, -5, -7, 20, 20))


def test_read_level_budget():
    with open_slide(SVS) as r:
        with pytest.raises(SlideError) as info:
            r.read_level(0, max_bytes=1_000_000)
    msg = str(info.value)
    assert str(2220 * 2967 * 3) in msg and "1000000" in msg
    assert MAX_DECODE_BYTES == 4 * 1024**3


def test_bad_arguments_are_value_errors():
    with open_slide(SVS) as r:
        with pytest.raises(ValueError):
            r.read_level(1)
        with pytest.raises(ValueError):
            r.read_region(0, 0, 0, -1, 5)
    with pytest.raises(ValueError):
        r.read_region(0, 0, 0, 5, 5)  # closed


# ---------------------------------------------------------------------------
# stripped uncompressed TIFF fixture


def test_kidney_stripped_tiff():
    with open_slide(KIDNEY) as r:
        assert r.format == "tiff"
        assert len(r.levels) == 1
        lv = r.levels[0]
        assert (lv.width, lv.height, lv.tile_size, lv.compression) == (1493, 901, None, "NONE")
        assert "stripped" in describe(r)
        img = r.read_level(0)
        assert img.shape == (901, 1493, 3) and img.dtype == np.uint8
        assert np.array_equal(img, tifffile.imread(KIDNEY))
        assert np.array_equal(r.read_region(0, 17, 300, 900, 211), img[300:511, 17:917])
        assert np.array_equal(r.read_region(0, 1400, 850, 200, 100), _padded_slice(img, 1400, 850, 200, 100))


# ---------------------------------------------------------------------------
# unreadable files


def test_broken_svs():
    with pytest.raises(SlideError) as info:
        with open_slide(BROKEN) as r:
            r.read_level(0)
    assert "broken.svs" in str(info.value)
    assert "SVS" in str(info.value)  # says what is supported


@pytest.mark.parametrize("size", [50, 200_000, 1_300_000])
def test_truncated_svs(tmp_path, size):
    path = tmp_path / "truncated.svs"
    path.write_bytes(SVS.read_bytes()[:size])
    try:
        with open_slide(path) as r:
            r.read_level(0)
    except SlideError as exc:
        assert "truncated.svs" in str(exc)
    # any other exception type fails the test


def test_truncated_tile_data(tmp_path, zlib_pyramid):
    src, _ = zlib_pyramid
    with tifffile.TiffFile(src) as tif:  # cut the file inside level-0 tile data
        cut = int(tif.pages[0].dataoffsets[5]) + 10
    path = tmp_path / "cut.tif"
    path.write_bytes(src.read_bytes()[:cut])
    with pytest.raises(SlideError, match="cut.tif"):
        with open_slide(path) as r:
            r.read_level(0)


def test_text_file(tmp_path):
    path = tmp_path / "notes.txt"
    path.write_text("this is not a slide\n" * 20)
    with pytest.raises(SlideError, match="not recognised"):
        open_slide(path)


def test_dicom_file(tmp_path):
    path = tmp_path / "slide.dcm"
    path.write_bytes(b"\0" * 128 + b"DICM" + b"\0" * 200)
    with pytest.raises(
        SlideError, match="slide.dcm: DICOM header unreadable|slide.dcm: a DICOM file but not a whole-slide image"
    ):
        open_slide(path)


def test_missing_file(tmp_path):
    with pytest.raises(SlideError, match="not found"):
        open_slide(tmp_path / "nope.svs")


def test_corrupt_tile_is_slide_error(tmp_path):
    base = _image(256, 256)
    path = tmp_path / "corrupt.tif"
    tifffile.imwrite(path, base, tile=(128, 128), compression="jpeg", photometric="rgb")
    data = bytearray(path.read_bytes())
    with tifffile.TiffFile(path) as tif:
        off, n = int(tif.pages[0].dataoffsets[0]), int(tif.pages[0].databytecounts[0])
    data[off : off + n] = b"\x13" * n  # garbage JPEG
    path.write_bytes(bytes(data))
    with open_slide(path) as r:
        with pytest.raises(SlideError, match="corrupt.tif"):
            r.read_region(0, 0, 0, 10, 10)
        # undamaged tiles still read
        assert r.read_region(0, 128, 128, 10, 10).shape == (10, 10, 3)


# ---------------------------------------------------------------------------
# pyramids written here


def test_jpeg_pyramid(tmp_path):
    base = _image(600, 520)
    path = tmp_path / "pyramid.tif"
    _write_pyramid(path, base, "jpeg")
    with open_slide(path) as r:
        assert r.format == "tiff"
        assert [(lv.width, lv.height) for lv in r.levels] == [(520, 600), (260, 300), (130, 150)]
        assert [lv.downsample for lv in r.levels] == [1.0, 2.0, 4.0]
        assert all(lv.tile_size == (128, 128) and lv.compression == "JPEG" for lv in r.levels)
        for level, expected in enumerate([base, base[::2, ::2], base[::4, ::4]]):
            img = r.read_level(level)
            assert img.shape == expected.shape and img.dtype == np.uint8
            assert np.abs(img.astype(int) - expected).mean() < 8  # lossy
            region = r.read_region(level, 50, 70, 150, 90)
            assert np.array_equal(region, _padded_slice(img, 50, 70, 150, 90))


def test_zlib_pyramid_exact(zlib_pyramid):
    path, base = zlib_pyramid
    with open_slide(path) as r:
        assert [lv.downsample for lv in r.levels] == [1.0, 2.0, 4.0]
        assert r.levels[0].compression == "ADOBE_DEFLATE"
        for level, expected in enumerate([base, base[::2, ::2], base[::4, ::4]]):
            assert np.array_equal(r.read_level(level), expected)
            assert np.array_equal(r.read_region(level, 100, 30, 140, 200), _padded_slice(expected, 100, 30, 140, 200))


def test_ome_tiff(tmp_path):
    base = _image(512, 384, seed=2)
    path = tmp_path / "pyramid.ome.tif"
    _write_pyramid(
        path,
        base,
        "zlib",
        ome=True,
        PhysicalSizeX=0.25,
        PhysicalSizeXUnit="µm",
        PhysicalSizeY=0.25,
        PhysicalSizeYUnit="µm",
    )
    with open_slide(path) as r:
        assert r.format == "ome-tiff"
        assert [lv.downsample for lv in r.levels] == [1.0, 2.0, 4.0]
        assert r.mpp == pytest.approx(0.25)
        assert r.dimensions == (384, 512)
        assert np.array_equal(r.read_level(1), base[::2, ::2])
        assert np.array_equal(r.read_region(2, 10, 20, 30, 40), base[::4, ::4][20:60, 10:40])
        assert "ome-tiff" in describe(r) and "0.25" in describe(r)


def test_ome_nanometre_unit(tmp_path):
    path = tmp_path / "nm.ome.tif"
    tifffile.imwrite(
        path,
        _image(64, 64),
        photometric="rgb",
        ome=True,
        metadata={"axes": "YXS", "PhysicalSizeX": 500, "PhysicalSizeXUnit": "nm"},
    )
    with open_slide(path) as r:
        assert r.mpp == pytest.approx(0.5)


def test_mpp_from_tiff_resolution(tmp_path):
    path = tmp_path / "res.tif"
    # 0.5 µm/px = 20000 px/cm
    tifffile.imwrite(path, _image(64, 64), photometric="rgb", resolution=(20000, 20000), resolutionunit="CENTIMETER")
    with open_slide(path) as r:
        assert r.mpp == pytest.approx(0.5)
    path = tmp_path / "nores.tif"
    tifffile.imwrite(path, _image(64, 64), photometric="rgb")
    with open_slide(path) as r:
        assert r.mpp is None
        assert "unknown" in describe(r)


@pytest.mark.skipif(not imagecodecs.JPEG2K.available, reason="imagecodecs built without JPEG 2000")
def test_jpeg2000_tiled(tmp_path):
    base = _image(300, 260)
    path = tmp_path / "j2k.tif"
    tifffile.imwrite(path, base, tile=(128, 128), compression="jpeg2000", photometric="rgb")
    with open_slide(path) as r:
        assert r.levels[0].compression == "JPEG2000"
        img = r.read_level(0)
        assert img.shape == (300, 260, 3)
        assert np.abs(img.astype(int) - base).mean() < 8
        assert np.array_equal(r.read_region(0, 100, 100, 100, 100), img[100:200, 100:200])


def test_planar_separate_rgb(tmp_path):
    base = _image(200, 300)
    path = tmp_path / "planar.tif"
    tifffile.imwrite(
        path, np.moveaxis(base, -1, 0), photometric="rgb", planarconfig="separate", tile=(64, 64), compression="zlib"
    )
    with open_slide(path) as r:
        assert np.array_equal(r.read_level(0), base)
        assert np.array_equal(r.read_region(0, 70, 30, 100, 100), base[30:130, 70:170])


# ---------------------------------------------------------------------------
# pixel format conversion


def test_rgba_composited_on_white(tmp_path):
    rgba = np.zeros((64, 80, 4), np.uint8)
    rgba[..., 0] = 200
    rgba[:, :40, 3] = 255  # opaque red-ish left half
    rgba[:, 40:, 3] = 0  # transparent right half -> white
    path = tmp_path / "rgba.tif"
    tifffile.imwrite(path, rgba, photometric="rgb", extrasamples="unassalpha")
    with open_slide(path) as r:
        img = r.read_level(0)
    assert img.shape == (64, 80, 3)
    assert (img[:, :40] == [200, 0, 0]).all()
    assert (img[:, 40:] == 255).all()


def test_grayscale_to_rgb(tmp_path):
    gray = _image(50, 60)[..., 0]
    path = tmp_path / "gray.tif"
    tifffile.imwrite(path, gray, photometric="minisblack", tile=(32, 32))
    with open_slide(path) as r:
        img = r.read_level(0)
        assert np.array_equal(r.read_region(0, 20, 10, 30, 30), img[10:40, 20:50])
    assert img.shape == (50, 60, 3)
    assert np.array_equal(img, np.repeat(gray[..., None], 3, axis=-1))


def test_palette_to_rgb(tmp_path):
    index = (np.arange(40 * 30).reshape(40, 30) % 4).astype(np.uint8)
    colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 20, 30]], np.uint16)
    cmap = np.zeros((3, 256), np.uint16)
    cmap[:, :4] = colors.T * 257  # TIFF colormaps are 16-bit
    path = tmp_path / "palette.tif"
    tifffile.imwrite(path, index, photometric="palette", colormap=cmap)
    with open_slide(path) as r:
        img = r.read_level(0)
    assert img.shape == (40, 30, 3)
    assert np.array_equal(img, colors[index].astype(np.uint8))


@pytest.mark.parametrize(
    "data, kwargs",
    [
        (np.zeros((5, 32, 32), np.uint16), {"photometric": "minisblack", "planarconfig": "separate"}),
        (np.zeros((32, 32, 3), np.uint16), {"photometric": "rgb"}),
        (np.zeros((32, 32, 3), np.float32), {"photometric": "rgb"}),
        (np.zeros((6, 32, 32), np.uint8), {"photometric": "minisblack", "planarconfig": "separate"}),
    ],
    ids=["uint16-5ch", "uint16-rgb", "float-rgb", "uint8-6ch"],
)
def test_unsupported_pixel_formats(tmp_path, data, kwargs):
    path = tmp_path / "multiplex.tif"
    tifffile.imwrite(path, data, **kwargs)
    with pytest.raises(SlideError, match="unsupported.*convert to 8-bit RGB first") as info:
        open_slide(path)
    assert "multiplex.tif" in str(info.value)


# ---------------------------------------------------------------------------
# property: regions are padded slices of the level


@settings(deadline=None, max_examples=40)
@given(data=st.data())
def test_random_regions_match_level(zlib_pyramid, data):
    path, base = zlib_pyramid
    full = [base, base[::2, ::2], base[::4, ::4]]
    level = data.draw(st.integers(0, 2), label="level")
    H, W = full[level].shape[:2]
    x = data.draw(st.integers(-40, W), label="x")
    y = data.draw(st.integers(-40, H), label="y")
    w = data.draw(st.integers(1, 300), label="w")
    h = data.draw(st.integers(1, 300), label="h")
    with open_slide(path) as r:
        region = r.read_region(level, x, y, w, h)
    assert region.shape == (h, w, 3) and region.dtype == np.uint8
    assert np.array_equal(region, _padded_slice(full[level], x, y, w, h))


@pytest.mark.parametrize("width", [2_000_000, 0])
def test_absurd_dimensions_refused(tmp_path, width):
    path = tmp_path / "huge.tif"
    tifffile.imwrite(path, _image(16, 16), photometric="rgb")
    with tifffile.TiffFile(path) as tif:
        tag = tif.pages[0].tags["ImageWidth"]
        offset, dtype = tag.valueoffset, tag.dtype
    assert int(dtype) == 4  # LONG
    data = bytearray(path.read_bytes())
    data[offset : offset + 4] = np.array([width], "<u4").tobytes()
    path.write_bytes(bytes(data))
    with pytest.raises(SlideError, match="huge.tif"):
        with open_slide(path) as r:
            r.read_level(0)


def test_missing_tile_is_white(tmp_path):
    base = _image(256, 256)
    path = tmp_path / "sparse.tif"
    tifffile.imwrite(path, base, tile=(128, 128), compression="zlib", photometric="rgb")
    with tifffile.TiffFile(path) as tif:
        tag = tif.pages[0].tags["TileByteCounts"]
        offset, dtype = tag.valueoffset, tag.dtype
    assert int(dtype) == 4  # LONG
    data = bytearray(path.read_bytes())
    data[offset : offset + 4] = b"\0\0\0\0"  # tile 0 absent (sparse file)
    path.write_bytes(bytes(data))
    with open_slide(path) as r, pytest.warns(UserWarning, match="absent from the file.*white"):
        img = r.read_level(0)
    assert (img[:128, :128] == 255).all()
    assert np.array_equal(img[128:, :], base[128:, :])
    assert np.array_equal(img[:128, 128:], base[:128, 128:])
