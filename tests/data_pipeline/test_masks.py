"""Tests for data_tools.masks: pixel-centre rasterisation of polygons and the Otsu tissue mask."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from PIL import Image
from shapely.affinity import rotate
from shapely.geometry import MultiPolygon, Polygon, box

from data_tools.masks import rasterize, tissue_mask
from data_tools.slide_files.open import open_slide

ROOT = Path(__file__).resolve().parents[2]
SVS = ROOT / "histojax" / "data" / "CMU-1-Small-Region.svs"


# ---------------------------------------------------------------------------
# rasterize


def test_square_with_hole_exact_area():
    outer = [(10, 10), (50, 10), (50, 40), (10, 40)]
    hole = [(20, 20), (30, 20), (30, 30), (20, 30)]
    poly = Polygon(outer, [hole])
    mask = rasterize(poly, 64, 48, 1.0)
    assert mask.shape == (48, 64) and mask.dtype == bool
    assert mask.sum() == poly.area == 40 * 30 - 10 * 10
    assert not mask[25, 25]  # inside the hole
    assert mask[15, 15]
    assert not mask[5, 5]
    # row i / column j convention: the square covers columns 10..49, rows 10..39
    assert mask[10, 10] and mask[39, 49] and not mask[40, 49] and not mask[39, 50]


def test_downsample_four_aligned_square():
    square = box(16, 32, 16 + 64, 32 + 128)  # 4-aligned, 64 × 128 level-0 px
    mask = rasterize(square, 50, 50, 4.0)
    assert mask.sum() == square.area / 16 == 16 * 32
    rows, cols = np.nonzero(mask)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (8, 39, 4, 19)


def test_multipolygon_two_disjoint_squares():
    geom = MultiPolygon([box(0, 0, 10, 10), box(20, 5, 35, 25)])
    mask = rasterize(geom, 40, 30, 1.0)
    assert mask.sum() == geom.area == 100 + 15 * 20
    assert mask[:10, :10].all()
    assert not mask[:, 10:20].any()


@pytest.mark.parametrize("geometry", [None, Polygon(), MultiPolygon()])
def test_empty_geometry_is_all_false(geometry):
    mask = rasterize(geometry, 17, 9, 2.0)
    assert mask.shape == (9, 17)
    assert not mask.any()


def test_polygon_partly_off_canvas():
    poly = box(-20, -10, 15, 12)  # inside part: [0, 15) × [0, 12)
    mask = rasterize(poly, 30, 20, 1.0)
    assert mask.shape == (20, 30)
    assert mask.sum() == 15 * 12
    far = box(50_000, 80_000, 120_000, 150_000)  # CAMELYON-scale coordinates, entirely off canvas
    assert not rasterize(far, 30, 20, 1.0).any()
    huge = box(-1e5, -1e5, 1e5, 1e5)  # covers the whole canvas
    assert rasterize(huge, 30, 20, 1.0).all()


@settings(deadline=None, max_examples=50)
@given(
    x0=st.integers(40, 90),
    y0=st.integers(40, 90),
    w=st.integers(1, 50),
    h=st.integers(1, 50),
    rotated=st.booleans(),
)
def test_rasterized_count_close_to_area(x0, y0, w, h, rotated):
    geom = box(x0, y0, x0 + w, y0 + h)
    if rotated:
        geom = rotate(geom, 45, origin="centroid")
    mask = rasterize(geom, 200, 200, 1.0)
    assert abs(int(mask.sum()) - geom.area) <= geom.length + 4
    if not rotated:
        assert mask.sum() == w * h  # integer-aligned: exact


# ---------------------------------------------------------------------------
# tissue_mask


@pytest.fixture(scope="module")
def svs_coarse() -> np.ndarray:
    """The SVS at downsample 16 (box average), like the coarsest bundle level."""
    with open_slide(SVS) as reader:
        rgb = reader.read_level(0)
    h, w = rgb.shape[0] // 16, rgb.shape[1] // 16
    return np.asarray(Image.fromarray(rgb).resize((w, h), Image.Resampling.BOX, box=(0, 0, w * 16, h * 16)))


def test_tissue_mask_on_svs(svs_coarse):
    mask = tissue_mask(svs_coarse)
    assert mask.shape == svs_coarse.shape[:2] and mask.dtype == bool
    assert 0.15 < mask.mean() < 0.85


def test_tissue_mask_all_white_is_empty():
    white = np.full((40, 60, 3), 255, dtype=np.uint8)
    mask = tissue_mask(white)
    assert mask.shape == (40, 60)
    assert not mask.any()


def test_tissue_mask_faint_glass_noise_is_empty():
    rng = np.random.default_rng(0)
    glass = np.clip(240 + rng.normal(0, 2, (50, 50, 3)), 0, 255).astype(np.uint8)
    assert tissue_mask(glass).mean() < 0.01
