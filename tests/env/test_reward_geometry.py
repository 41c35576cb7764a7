"""The reward's tumour fraction equals an independent shapely computation on real CAMELYON16
geometry (tumor_039, with its exclusion holes), scaled onto a synthetic slide."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import shapely
import shapely.affinity
import tifffile
from hypothesis import given, settings
from hypothesis import strategies as st

import histojax
from data_tools.annotations import load_annotations
from data_tools.bundle import build_bundle
from histojax.core.views import view_tumour_fraction

DATA = Path(__file__).parents[1] / "data" / "annotations"
SCALE = 1 / 16  # tumor_039's 26k × 22k px tumour box becomes ~1.6k × 1.4k px
TILE = 64


@pytest.fixture(scope="module")
def camelyon_env(tmp_path_factory):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # CAMELYON outlines self-intersect: repaired with a warning
        ann = load_annotations(DATA / "tumor_039.xml")
    assert ann.exclusion.area > 0  # the holes are there and subtracted
    minx, miny, _, _ = ann.tumour.bounds
    geom = shapely.affinity.scale(ann.tumour, SCALE, SCALE, origin=(0, 0))
    geom = shapely.affinity.translate(geom, -minx * SCALE + 40, -miny * SCALE + 30)
    width, height = int(geom.bounds[2]) + 60, int(geom.bounds[3]) + 50
    root = tmp_path_factory.mktemp("camelyon")
    rng = np.random.default_rng(0)
    tifffile.imwrite(
        root / "synthetic.tif",
        rng.integers(150, 255, (height, width, 3), dtype=np.uint8),
        photometric="rgb",
        tile=(256, 256),
    )
    (root / "tumour.geojson").write_text(
        json.dumps({"type": "Feature", "properties": {"label": "tumour"}, "geometry": shapely.geometry.mapping(geom)})
    )
    bundle = build_bundle(
        root / "synthetic.tif",
        root / "bundle",
        annotations_path=root / "tumour.geojson",
        level_sets=(7,),
        tile_size=TILE,
        progress=False,
    )
    env, params = histojax.make("HistoJAX-Hard-v0", slide=bundle)
    fraction = jax.jit(lambda z, x, y, p: view_tumour_fraction(p.slide, z, x, y, TILE))
    return env, params, geom, fraction


@settings(deadline=None, max_examples=150, derandomize=True)
@given(z=st.integers(0, 6), u=st.floats(0, 1), v=st.floats(0, 1))
def test_tumour_fraction_matches_shapely(camelyon_env, z, u, v):
    env, params, geom, fraction = camelyon_env
    w, h = int(params.slide.level_width[z]), int(params.slide.level_height[z])
    x, y = round(u * (w - TILE)), round(v * (h - TILE))
    d = float(params.slide.downsample[z])
    box = shapely.box(x * d, y * d, (x + TILE) * d, (y + TILE) * d)  # the view in level-0 px
    expected = geom.intersection(box).area / box.area
    got = float(fraction(jnp.int32(z), jnp.int32(x), jnp.int32(y), params))
    # rasterising errs only in pixels the outline crosses: bound by outline length in level px
    boundary_px = geom.boundary.intersection(box).length / d
    tolerance = (2 * boundary_px + 4) / TILE**2
    assert abs(got - expected) <= tolerance, (z, x, y, got, expected, tolerance)


def test_fraction_is_exact_far_from_the_outline(camelyon_env):
    env, params, geom, fraction = camelyon_env
    z = 6
    inner = geom.buffer(-2 * TILE)
    px, py = inner.representative_point().coords[0]
    x, y = int(px) - TILE // 2, int(py) - TILE // 2
    assert float(fraction(jnp.int32(z), jnp.int32(x), jnp.int32(y), params)) == 1.0
    assert float(fraction(jnp.int32(z), jnp.int32(0), jnp.int32(0), params)) == 0.0
