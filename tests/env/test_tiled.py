"""Tiled bundles (sparse tile pools): the same observations and rewards as dense bundles, less memory.

The embedded sample slide is built dense and tiled (every tile kept, background shared, and built in
one-tile-row bands); views are compared exactly. A gigapixel-style case (``synth-large``) is slow.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_examples import examples

import histojax
from data_tools.bundle import FORMAT_VERSION, TILED_FORMAT_VERSION, build_bundle, load_bundle, read_metadata
from data_tools.errors import BundleError
from histojax.core.views import view_pixels, view_tumour_fraction
from histojax.loading import stack_slides

DATA = Path(histojax.__file__).parent / "data"
SVS, XML = DATA / "CMU-1-Small-Region.svs", DATA / "CMU-1-Small-Region.target.xml"
T = 128
KEY = jax.random.PRNGKey(0)


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiled")
    kw = dict(annotations_path=XML, tile_size=T, progress=False)
    return {
        "dense": build_bundle(SVS, root / "dense", **kw),
        "all": build_bundle(SVS, root / "all", storage="tiled", share_background=False, **kw),
        "shared": build_bundle(SVS, root / "shared", storage="tiled", **kw),
        "banded": build_bundle(SVS, root / "banded", storage="tiled", share_background=False, band_bytes=1, **kw),
    }


@pytest.fixture(scope="module")
def hard(bundles):
    return {name: histojax.make("HistoJAX-Hard-v0", slide=path) for name, path in bundles.items()}


@functools.lru_cache(maxsize=None)
def _views_fn():
    return jax.jit(
        jax.vmap(
            lambda s, z, x, y: (view_pixels(s, z, x, y, T), view_tumour_fraction(s, z, x, y, T)),
            in_axes=(None, 0, 0, 0),
        )
    )


def _random_views(slide, n, seed=0):
    rng = np.random.default_rng(seed)
    z = rng.integers(0, slide.level_width.shape[0], n)
    w, h = np.asarray(slide.level_width)[z], np.asarray(slide.level_height)[z]
    x = (rng.random(n) * (w - T + 1)).astype(np.int32)
    y = (rng.random(n) * (h - T + 1)).astype(np.int32)
    return [jnp.asarray(v, jnp.int32) for v in (z, x, y)]


def test_metadata_and_versions(bundles):
    dense, tiled = read_metadata(bundles["dense"]), read_metadata(bundles["shared"])
    assert dense["format_version"] == FORMAT_VERSION == 1 and dense["storage"] == "dense"
    assert tiled["format_version"] == TILED_FORMAT_VERSION == 2 and tiled["storage"] == "tiled"
    for lv in tiled["levels"]:
        assert lv["storage"] == "tiled" and lv["pool_tiles"] >= 1 and lv["sat_pool_tiles"] >= 2
        assert (
            lv["device_bytes"]
            == lv["pool_tiles"] * T * T * 3
            + lv["sat_pool_tiles"] * (T + 1) ** 2 * 4
            + 8 * lv["grid"][0] * lv["grid"][1]
        )
    assert tiled["device_bytes"] == sum(lv["device_bytes"] for lv in tiled["levels"])
    assert tiled["build"]["peak_rss_bytes"] > 0
    # the kept tiles are the non-blank ones; every level of a keep-all bundle keeps its whole grid
    full = read_metadata(bundles["all"])
    assert all(lv["kept_tiles"] == lv["grid"][0] * lv["grid"][1] for lv in full["levels"])
    assert sum(lv["kept_tiles"] for lv in tiled["levels"]) < sum(lv["kept_tiles"] for lv in full["levels"])


def test_host_levels_equal_dense(bundles):
    """Every level of the keep-all and the banded (one tile row at a time) builds equals the dense level."""
    dense = load_bundle(bundles["dense"])
    for name in ("all", "banded"):
        tiled = load_bundle(bundles[name])
        assert tiled.storage == "tiled"
        for k in range(len(dense.pixels)):
            np.testing.assert_array_equal(np.asarray(tiled.pixels[k]), dense.pixels[k])
            np.testing.assert_array_equal(np.asarray(tiled.tumour[k]), dense.tumour[k])
            assert tiled.tumour[k].sum() == int(dense.tumour[k].sum())
        np.testing.assert_array_equal(tiled.tissue, dense.tissue)


def test_keep_all_views_equal_dense_vectorised(hard):
    (_, pd), (_, pa) = hard["dense"], hard["all"]
    args = _random_views(pd.slide, 3000)
    pix_d, frac_d = _views_fn()(pd.slide, *args)
    pix_a, frac_a = _views_fn()(pa.slide, *args)
    np.testing.assert_array_equal(np.asarray(pix_a), np.asarray(pix_d))
    np.testing.assert_array_equal(np.asarray(frac_a), np.asarray(frac_d))
    assert float(frac_d.max()) > 0.5  # some views hold tumour


def test_corner_and_edge_views_equal_dense(hard):
    """Views at the corners and edges of every level (the last partial tiles, the pool's first and last
    tiles) equal the dense ones."""
    (_, pd), (_, pa) = hard["dense"], hard["all"]
    zs, xs, ys = [], [], []
    for z in range(7):
        w, h = int(pd.slide.level_width[z]), int(pd.slide.level_height[z])
        for x in (0, 1, T - 1, w - T - 1, w - T):
            for y in (0, 1, T - 1, h - T - 1, h - T):
                zs.append(z), xs.append(max(0, min(x, w - T))), ys.append(max(0, min(y, h - T)))
    args = [jnp.asarray(v, jnp.int32) for v in (zs, xs, ys)]
    for a, b in zip(_views_fn()(pd.slide, *args), _views_fn()(pa.slide, *args)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@settings(deadline=None, max_examples=examples(60, 20), derandomize=True)
@given(z=st.integers(0, 6), fx=st.floats(0, 1), fy=st.floats(0, 1), aligned=st.booleans())
def test_views_match_dense(hard, z, fx, fy, aligned):
    """For any (z, x, y): keep-all = dense exactly; with a shared blank tile the pixels equal dense
    wherever the tile kept its pixels and are white where it is the blank tile; the tumour fraction is
    always exact."""
    (_, pd), (_, pa), (env_s, ps) = hard["dense"], hard["all"], hard["shared"]
    w, h = int(pd.slide.level_width[z]), int(pd.slide.level_height[z])
    x, y = int(fx * (w - T)), int(fy * (h - T))
    if aligned:
        x, y = x // T * T, y // T * T
    args = [jnp.asarray([v], jnp.int32) for v in (z, x, y)]
    pix_d, frac_d = (np.asarray(a[0]) for a in _views_fn()(pd.slide, *args))
    pix_a, frac_a = (np.asarray(a[0]) for a in _views_fn()(pa.slide, *args))
    pix_s, frac_s = (np.asarray(a[0]) for a in _views_fn()(ps.slide, *args))
    np.testing.assert_array_equal(pix_a, pix_d)
    assert frac_a == frac_d == frac_s
    index = env_s.bundles[0].pixels[z].index  # (gh, gw) pool index of each tile of level z (0 = blank)
    rows, cols = np.arange(y, y + T) // T, np.arange(x, x + T) // T
    kept = index[rows][:, cols] > 0
    np.testing.assert_array_equal(pix_s[kept], pix_d[kept])
    assert np.all(pix_s[~kept] == 255)


def test_glass_views_are_white_and_tissue_views_exact(hard):
    (_, pd), (env_s, ps) = hard["dense"], hard["shared"]
    z = 6
    index = env_s.bundles[0].pixels[z].index
    blank = np.argwhere(index == 0)
    kept = np.argwhere(index > 0)
    assert len(blank) and len(kept)
    for (ty, tx), white in [(blank[0], True), (kept[len(kept) // 2], False)]:
        s = histojax.EnvState(
            z=jnp.int32(z), x=jnp.int32(tx * T), y=jnp.int32(ty * T), t=jnp.int32(0), slide_index=jnp.int32(0)
        )
        obs_s = np.asarray(env_s.get_obs(s, ps))
        obs_d = np.asarray(env_s.get_obs(s, pd))
        if white:
            assert np.all(obs_s == 255)
        else:
            np.testing.assert_array_equal(obs_s, obs_d)


def _rollout(env, params, n_envs=16, n_steps=40):
    def run(key, params):  # params passed as an argument: the slide arrays must not become constants
        keys = jax.random.split(key, n_envs)
        obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)

        def body(carry, k):
            state = carry
            actions = jax.random.randint(k, (n_envs,), 0, 7)
            obs, state, reward, term, trunc, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
                jax.random.split(k, n_envs), state, actions, params
            )
            return state, (state.z, state.x, state.y, reward, info["tumour_fraction"], obs.sum(axis=(1, 2, 3)))

        return jax.lax.scan(body, state, jax.random.split(key, n_steps))[1]

    return jax.jit(run)(KEY, params)


def test_env_jit_vmap_scan_on_tiled(hard):
    """The env rolls out jitted, vmapped and scanned on a tiled bundle; the trajectory (states, rewards,
    tumour fractions) equals the dense one, and so do the observations of the keep-all bundle."""
    dense = _rollout(*hard["dense"])
    every = _rollout(*hard["all"])
    shared = _rollout(*hard["shared"])
    for a, b, c in list(zip(dense, every, shared))[:5]:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
    np.testing.assert_array_equal(np.asarray(dense[5]), np.asarray(every[5]))
    assert float(jnp.abs(dense[3]).max()) > 0


def test_device_bytes_and_budget(bundles, hard):
    (_, pd), (_, ps) = hard["dense"], hard["shared"]
    nbytes = lambda p: sum(int(a.nbytes) for a in jax.tree.leaves(p.slide))  # noqa: E731
    assert nbytes(ps) < nbytes(pd)
    assert ps.slide.pixels is None and ps.slide.tumour_sat is None and pd.slide.tile_pool is None
    meta = read_metadata(bundles["shared"])
    needed = sum(lv["device_bytes"] for lv in meta["levels"][:1])
    with pytest.raises(BundleError, match=r"need [\d,]+ bytes on the device"):
        histojax.make("HistoJAX-Hard-v0", slide=bundles["shared"], max_device_bytes=needed)


def test_much_glass_needs_far_fewer_bytes(tmp_path):
    """A slide that is 90 % glass: the tiled bundle's device bytes are a fraction of the dense ones, and
    within 2x of the tissue tiles' bytes."""
    from data_tools.datasets.synth.large_slide import make_large_slide

    tif = tmp_path / "glassy.tif"
    make_large_slide(tif, size=4096, tissue_fraction=0.1, progress=False)
    out = build_bundle(
        tif,
        tmp_path / "b",
        annotations_path=tif.with_suffix(".geojson"),
        storage="tiled",
        level_sets=(3,),
        progress=False,
    )
    meta = read_metadata(out)
    assert meta["storage"] == "tiled"
    finest = meta["levels"][0]
    assert finest["device_bytes"] < 0.3 * finest["dense_device_bytes"]
    assert finest["device_bytes"] < 2 * finest["kept_tiles"] * T * T * 3
    env, params = histojax.make("HistoJAX-Easy-v0", slide=out)
    obs, state = env.reset(KEY, params)
    assert obs.shape == (T, T, 3) and env.render(state, params).ndim == 3


def test_auto_is_dense_for_small_slides(tmp_path):
    out = build_bundle(SVS, tmp_path / "auto", annotations_path=XML, storage="auto", level_sets=(3,), progress=False)
    assert read_metadata(out)["storage"] == "dense"
    with pytest.raises(BundleError, match="storage must be one of"):
        build_bundle(SVS, tmp_path / "bad", storage="sparse", progress=False)


def test_datasets_stack_tiled_and_refuse_mixing(bundles, hard):
    env, params = histojax.make("HistoJAX-Hard-v0", slides=[bundles["all"], bundles["shared"]])
    slide = params.slide
    assert (
        slide.num_slides == 2
        and slide.tile_pool.shape[0]
        == hard["all"][1].slide.tile_pool.shape[0] + hard["shared"][1].slide.tile_pool.shape[0]
    )
    (_, pa), (_, ps) = hard["all"], hard["shared"]
    args = _random_views(pa.slide, 500, seed=3)
    for i, single in enumerate((pa, ps)):
        pix, frac = _views_fn()(slide.select(i), *args)
        ref_pix, ref_frac = _views_fn()(single.slide, *args)
        np.testing.assert_array_equal(np.asarray(pix), np.asarray(ref_pix))
        np.testing.assert_array_equal(np.asarray(frac), np.asarray(ref_frac))
    obs, state = jax.jit(env.reset)(KEY, params)
    assert obs.shape == (T, T, 3)
    with pytest.raises(ValueError, match="cannot mix dense and tiled"):
        stack_slides([hard["dense"][1].slide, ps.slide])


def test_cli_build_tiled(tmp_path, capsys):
    from data_tools.__main__ import main

    out = tmp_path / "cli"
    assert (
        main(["build", str(SVS), "--annotations", str(XML), "--out", str(out), "--levels", "3", "--storage", "tiled"])
        == 0
    )  # not --quiet: that prints only the `wrote` line, no level table
    text = capsys.readouterr().out
    assert "(tiled)" in text and "pool tiles" in text
    assert json.loads((out / "metadata.json").read_text())["storage"] == "tiled"


@pytest.mark.slow
@pytest.mark.parametrize("size", [20_000, 100_000])
def test_gigapixel_style_slide_end_to_end(tmp_path, size):
    """synth-large at 20,000 and at the full 100,000 px → tiled bundle (streamed) → the env at full
    resolution (the 100k case takes about 5 minutes and 4 GB of RAM on 2 cores)."""
    from data_tools.datasets.synth.large_slide import make_large_slide

    tif = tmp_path / "large.tif"
    prov = make_large_slide(tif, size=size, tissue_fraction=0.1, progress=False)
    assert prov["tiff_bytes"] < 200 * 2**20 * (size / 20_000) ** 2 and 0.05 < prov["tissue_fraction"] < 0.15
    # the build in a process of its own: its recorded peak is the build's, not this worker's earlier tests' (a reset
    # peak starts at the process's resident memory, which a long pytest worker holds several GB of)
    import subprocess
    import sys

    out = tmp_path / "b"
    code = (
        "import sys; from pathlib import Path; from data_tools.bundle import build_bundle; "
        "t = Path(sys.argv[1]); build_bundle(t, Path(sys.argv[2]), annotations_path=t.with_suffix('.geojson'), "
        "storage='auto', level_sets=(3,), progress=False)"
    )
    subprocess.run([sys.executable, "-c", code, str(tif), str(out)], check=True)
    meta = read_metadata(out)
    assert meta["storage"] == "tiled" and meta["build"]["peak_rss_bytes"] < 2 * 2**30
    finest = meta["levels"][0]
    assert (finest["width"], finest["height"]) == (size, size)
    assert finest["device_bytes"] < 2 * finest["kept_tiles"] * T * T * 3
    assert finest["tumour_pixels"] > 0
    env, params = histojax.make("HistoJAX-Easy-v0", slide=out)
    # a finest-level view on the tumour has a positive fraction; the rollout runs jitted/vmapped/scanned
    b = load_bundle(out, verify=False, levels=[0])
    ty, tx = (
        np.argwhere(b.tumour[0].index == 1)[0]
        if (b.tumour[0].index == 1).any()
        else np.argwhere(b.tumour[0].index > 0)[0]
    )
    s = histojax.EnvState(
        z=jnp.int32(2), x=jnp.int32(tx * T), y=jnp.int32(ty * T), t=jnp.int32(0), slide_index=jnp.int32(0)
    )
    assert float(view_tumour_fraction(params.slide, s.z, s.x, s.y, T)) > 0
    np.testing.assert_array_equal(
        np.asarray(env.get_obs(s, params)), b.pixels[0][ty * T : (ty + 1) * T, tx * T : (tx + 1) * T]
    )
    z, *_ = _rollout(env, params, n_envs=64, n_steps=50)
    assert int(np.asarray(z).max()) == 2


@pytest.mark.parametrize("region", [(300, 500, 1900, 2400), "polygon"])
def test_region_bundles_tiled_equal_dense(tmp_path, region):
    """Region bundles (a rectangle, a polygon painted white outside) built tiled keep-all equal dense."""
    from shapely.geometry import Polygon

    if region == "polygon":
        region = Polygon([(200, 300), (2000, 500), (1800, 2700), (400, 2400)])
    kw = dict(annotations_path=XML, level_sets=(3,), progress=False, region=region)
    dense = load_bundle(build_bundle(SVS, tmp_path / "d", **kw))
    tiled = load_bundle(build_bundle(SVS, tmp_path / "t", storage="tiled", share_background=False, band_bytes=1, **kw))
    for k in range(len(dense.pixels)):
        np.testing.assert_array_equal(np.asarray(tiled.pixels[k]), dense.pixels[k])
        np.testing.assert_array_equal(np.asarray(tiled.tumour[k]), dense.tumour[k])
    np.testing.assert_array_equal(tiled.tissue, dense.tissue)
    np.testing.assert_array_equal(tiled.region, dense.region)


def test_cli_synth_large(tmp_path, capsys):
    from data_tools.__main__ import main
    from data_tools.slide_files.open import open_slide

    out = tmp_path / "large.tif"
    assert main(["synth-large", str(out), "--size", "2048", "--tissue-fraction", "0.2", "--quiet"]) == 0
    assert "2048×2048 px" in capsys.readouterr().out
    with open_slide(out) as reader:
        assert reader.dimensions == (2048, 2048) and len(reader.levels) == 3
        assert reader.levels[0].tile_size == (256, 256) and reader.levels[0].compression == "JPEG"
    geo = json.loads(out.with_suffix(".geojson").read_text())
    assert {f["properties"]["label"] for f in geo["features"]} == {"tumour", "tissue"}
