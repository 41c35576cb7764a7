"""Your own encoder (``--encoder module:function``): a tiny JAX callable (tests/encoder_helpers.py) embeds a
bundle (``data_tools features``) and the C16 small set (``c16``); its name, version and spec are recorded; the
v1 ids observe it; an encoder that breaks a rule (shape, dtype, finiteness, an error, a built-in's name) is
refused in one line naming it, exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import encoder_helpers
import numpy as np
import pytest

from data_tools.__main__ import main as data_main
from data_tools.bundle_files.reading import read_metadata
from data_tools.errors import HistojaxDataError

SPEC = "encoder_helpers:tiny_colour"


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory) -> Path:
    """A 256 × 192 px synthetic slide, 32-px views, 3 zoom levels."""
    import tifffile

    from data_tools.bundle import build_bundle

    root = tmp_path_factory.mktemp("tiny")
    rng = np.random.default_rng(0)
    image = rng.integers(150, 255, (192, 256, 3)).astype(np.uint8)
    image[40:120, 60:200] = [200, 60, 150]
    tifffile.imwrite(root / "tiny.tif", image, photometric="rgb")
    return build_bundle(root / "tiny.tif", root / "bundle", level_sets=(3,), tile_size=32, progress=False)


def test_features_with_your_own_encoder_records_it_and_embeds_every_view(tiny_bundle, capsys):
    assert data_main(["features", str(tiny_bundle), "--encoder", SPEC, "--quiet", "--dtype", "float32"]) == 0
    meta = read_metadata(tiny_bundle)
    f = meta.features
    assert (f["encoder"], f["encoder_version"], f["encoder_spec"], f["dim"]) == ("tiny-colour", "1", SPEC, 6)
    assert "tiny-colour feature grid" in capsys.readouterr().out
    grid = np.load(tiny_bundle / f["levels"][0]["file"])
    assert grid.shape[-1] == 6 and np.isfinite(grid).all()


def test_features_grid_cell_equals_the_callable_on_the_view(tiny_bundle):
    import tifffile

    meta = read_metadata(tiny_bundle)
    if (meta.features or {}).get("encoder") != "tiny-colour":
        assert data_main(["features", str(tiny_bundle), "--encoder", SPEC, "--quiet", "--dtype", "float32"]) == 0
        meta = read_metadata(tiny_bundle)
    image = tifffile.imread(tiny_bundle.parent / "tiny.tif")
    finest = meta.features["levels"][0]  # level 0: the finest (downsample 1)
    grid = np.load(tiny_bundle / finest["file"])
    gh, gw = finest["grid"]
    assert (gh, gw) == (192 // 32, 256 // 32)
    want = np.asarray(encoder_helpers.tiny_colour(image[None, 32:64, 64:96]))[0]
    np.testing.assert_allclose(grid[1, 2], want, atol=1e-5)


def test_an_unnamed_callable_is_recorded_by_its_spec():
    from data_tools.features import encoder_record

    assert encoder_record("encoder_helpers:unnamed") == {
        "encoder": "encoder_helpers:unnamed",
        "encoder_version": None,
        "encoder_spec": "encoder_helpers:unnamed",
    }


@pytest.mark.parametrize(
    "name, problem",
    [
        ("wrong_shape", r"returned shape \(2,\) for 2 views; it must return \(N, D\)"),
        ("wrong_dtype", "returned dtype float64; it must return float32"),
        ("not_finite", "returned NaN or infinite values for 1 of 2 views"),
        ("raises", "failed on 2 views of 128x128 px: RuntimeError: weights not found"),
        ("steals_a_name", "named 'pcam-cnn', a built-in encoder's name"),
        ("no_such_function", "module 'encoder_helpers' has no 'no_such_function'"),
    ],
)
def test_a_broken_encoder_is_refused_in_one_line_naming_it(tiny_bundle, tmp_path, capsys, name, problem):
    spec = f"encoder_helpers:{name}"
    before = sorted(p.name for p in tiny_bundle.iterdir())
    assert data_main(["features", str(tiny_bundle), "--encoder", spec, "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and spec in err[0] and __import__("re").search(problem, err[0]), err
    assert sorted(p.name for p in tiny_bundle.iterdir()) == before  # nothing half-written
    # the same from c16, before any slide is made
    assert data_main(["c16", "--small", "--out", str(tmp_path / "c16"), "--encoder", spec, "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and spec in err[0], err
    assert not (tmp_path / "c16").exists()


def test_a_missing_module_is_named(capsys):
    from histojax.cli import main

    assert main(["dataset", "/nonexistent-slides", "--out", "/tmp/never", "--encoder", "no_such_module_x:f"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--encoder no_such_module_x:f: cannot import 'no_such_module_x'" in err[0], err


@pytest.mark.slow  # the C16 small set built and embedded: ~40 s on 2 shared cores
def test_c16_small_with_your_own_encoder_and_the_v1_ids_observe_it(tmp_path):
    """The C16 small set embedded with the tiny encoder (feature-only): dataset.json records its name, version and
    spec, and HistoJAX-C16-Easy-v1 (before: pcam-cnn grids only) observes its 6 numbers."""
    import jax

    import histojax
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = tmp_path / "c16"
    ds = make_c16_dataset(out, small=True, features=SPEC, no_pixels=True, progress=False)
    assert (ds["encoder"], ds["encoder_version"], ds["encoder_spec"]) == ("tiny-colour", "1", SPEC)
    assert json.loads((out / "dataset.json").read_text())["encoder"] == "tiny-colour"
    env, params = histojax.make("HistoJAX-C16-Easy-v1", dataset=out, split="train", verify=False)
    obs, _ = env.reset(jax.random.PRNGKey(0), params)
    obs = obs["features"] if isinstance(obs, dict) else obs
    assert obs.shape[-1] == 6 and np.isfinite(np.asarray(obs)).all()


def test_v1_ids_refuse_a_dataset_without_feature_grids_but_take_any_encoders(tmp_path):
    from histojax.datasets import check_dataset
    from histojax.registry import C16_V1

    base = {"kind": "histojax true-scale CAMELYON16 benchmark (data_tools c16)", "format": 2}
    for encoder in ("pcam-cnn", "tiny-colour", "imported"):
        (tmp_path / "dataset.json").write_text(json.dumps({**base, "encoder": encoder}))
        check_dataset(tmp_path, C16_V1, "HistoJAX-C16-Hard-v1")
    (tmp_path / "dataset.json").write_text(json.dumps({**base, "encoder": None}))
    with pytest.raises(HistojaxDataError, match="pcam-cnn features, and this dataset records no feature grids"):
        check_dataset(tmp_path, C16_V1, "HistoJAX-C16-Hard-v1")
