"""Region bundles: a bundle of one rectangle (or polygon) of the slide is a region scenario."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest
import shapely

from data_tools.annotations import load_annotations
from data_tools.bundle import build_bundle, default_magnification_range, load_bundle
from data_tools.errors import BundleError
from data_tools.slide_files.open import open_slide
from histojax.sample import SAMPLE_ANNOTATIONS, SAMPLE_SLIDE

MARGIN = 300


@pytest.fixture(scope="module")
def target():
    return load_annotations(SAMPLE_ANNOTATIONS).tumour


@pytest.fixture(scope="module")
def box(target):
    with open_slide(SAMPLE_SLIDE) as r:
        w, h = r.dimensions
    b = target.bounds
    return (
        max(0, int(b[0]) - MARGIN),
        max(0, int(b[1]) - MARGIN),
        min(w, int(b[2]) + MARGIN),
        min(h, int(b[3]) + MARGIN),
    )


@pytest.fixture(scope="module")
def region_bundle(tmp_path_factory, box):
    out = tmp_path_factory.mktemp("region") / "bundle"
    return build_bundle(SAMPLE_SLIDE, out, annotations_path=SAMPLE_ANNOTATIONS, region=box, progress=False)


def test_region_bundle_sizes_pixels_metadata(region_bundle, box):
    meta = json.loads((region_bundle / "metadata.json").read_text())
    x0, y0, x1, y1 = box
    assert meta["region"]["box"] == list(box) and meta["region"]["kind"] == "rectangle"
    assert meta["magnification_range"] == default_magnification_range(x1 - x0, y1 - y0, 128)
    finest = meta["levels"][0]
    assert finest["downsample"] == 1.0
    assert (finest["content_width"], finest["content_height"]) == (x1 - x0, y1 - y0)
    for lv in meta["levels"]:
        assert lv["content_width"] == int((x1 - x0) // lv["downsample"])
    bundle = load_bundle(region_bundle)
    with open_slide(SAMPLE_SLIDE) as r:
        expected = r.read_region(0, x0, y0, x1 - x0, y1 - y0)
    np.testing.assert_array_equal(bundle.pixels[0], expected)
    assert bundle.region is not None and bundle.region.all()  # a rectangle: every centre allowed


def test_tumour_area_preserved(region_bundle, target, box):
    meta = json.loads((region_bundle / "metadata.json").read_text())
    inside = shapely.intersection(target, shapely.box(*box)).area
    assert inside == pytest.approx(target.area)  # the margin keeps the whole target
    assert meta["annotations"]["tumour_area_px"] == pytest.approx(inside)
    assert meta["levels"][0]["tumour_pixels"] == pytest.approx(inside, rel=0.01)
    # the annotation stored in the bundle is in region px
    geo = json.loads((region_bundle / "annotations.geojson").read_text())
    stored = shapely.geometry.shape(geo["features"][0]["geometry"])
    assert stored.bounds[0] == pytest.approx(target.bounds[0] - box[0])
    assert stored.bounds[1] == pytest.approx(target.bounds[1] - box[1])


def test_view_never_leaves_region(region_bundle, box):
    import histojax

    env, params = histojax.make("HistoJAX-Hard-v0", slide=region_bundle)
    n_envs, n_steps, t = 16, 150, env.tile_size

    @jax.jit
    def rollout(key):
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, n_envs), params)

        def body(state, k):
            ka, ks = jax.random.split(k)
            a = jax.random.randint(ka, (n_envs,), 0, 7)
            _, state, reward, *_ = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(ks, n_envs), state, a, params
            )
            return state, (state.z, state.x, state.y, reward)

        return jax.lax.scan(body, state, jax.random.split(key, n_steps))[1]

    z, x, y, reward = (np.asarray(v) for v in rollout(jax.random.PRNGKey(0)))
    widths, heights = np.asarray(params.slide.level_width), np.asarray(params.slide.level_height)
    ds = np.asarray(params.slide.downsample)
    assert (x >= 0).all() and (y >= 0).all()
    assert (x <= widths[z] - t).all() and (y <= heights[z] - t).all()
    # in level-0 px the view stays inside the region
    assert ((x + t) * ds[z] <= box[2] - box[0] + ds[z]).all()
    assert ((y + t) * ds[z] <= box[3] - box[1] + ds[z]).all()
    assert np.isfinite(reward).all() and (z == 6).any()


def test_polygon_region_starts_inside(tmp_path):
    import histojax

    poly = shapely.Polygon([(700, 1300), (2200, 1400), (1400, 2960)])
    out = build_bundle(
        SAMPLE_SLIDE,
        tmp_path / "poly",
        annotations_path=SAMPLE_ANNOTATIONS,
        region=poly,
        level_sets=(3,),
        progress=False,
    )
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["region"]["kind"] == "polygon" and meta["region"]["box"] == [700, 1300, 2200, 2960]
    bundle = load_bundle(out)
    # outside the polygon: white glass, no tissue, no start
    assert (bundle.pixels[0][5, -5] == 255).all() and not bundle.region[2, -2] and not bundle.tissue[2, -2]
    env, params = histojax.make("HistoJAX-Easy-v0", slide=out)
    _, states = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))(jax.random.split(jax.random.PRNGKey(1), 256), params)
    c = env.tile_size // 2
    coarsest_mask = bundle.region  # stored at the coarsest level
    assert coarsest_mask[np.asarray(states.y) + c, np.asarray(states.x) + c].all()


def test_group_region_and_cli(tmp_path):
    from data_tools.__main__ import main

    out = tmp_path / "grp"
    assert (
        main(
            [
                "build",
                str(SAMPLE_SLIDE),
                "--annotations",
                str(SAMPLE_ANNOTATIONS),
                "--out",
                str(out),
                "--region-group",
                "tumour",
                "--region-margin",
                "50",
                "--levels",
                "3",
                "--quiet",
            ]
        )
        == 0
    )
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["region"]["kind"] == "group" and meta["region"]["group"] == "tumour"
    assert meta["region"]["box"] == [1010, 1570, 1930, 2967]
    out2 = tmp_path / "box"
    assert (
        main(
            ["build", str(SAMPLE_SLIDE), "--out", str(out2), "--region", "100,200,600,700", "--levels", "3", "--quiet"]
        )
        == 0
    )
    assert json.loads((out2 / "metadata.json").read_text())["region"]["box"] == [100, 200, 600, 700]
    with pytest.raises(SystemExit):  # argparse: usage error, status 2
        main(["build", str(SAMPLE_SLIDE), "--out", str(tmp_path / "bad"), "--region", "1,2,3"])
    assert main(["build", str(SAMPLE_SLIDE), "--out", str(tmp_path / "bad"), "--region", "5000,5000,6000,6000"]) == 2


@pytest.mark.parametrize(
    "region, match",
    [
        ((5000, 5000, 6000, 6000), "smaller than one"),
        ((0, 0, 50, 50), "smaller than one"),
        ((10, 10, 5, 500), "x0 < x1"),
        ("tissue", "no tissue polygon"),
        ("no-such-group", "no polygon in that group"),
    ],
)
def test_bad_regions(tmp_path, region, match):
    with pytest.raises(BundleError, match=match):
        build_bundle(SAMPLE_SLIDE, tmp_path / "b", annotations_path=SAMPLE_ANNOTATIONS, region=region, progress=False)
    assert not (tmp_path / "b").exists()
