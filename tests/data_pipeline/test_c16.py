"""The true-scale CAMELYON16 benchmark (``data_tools c16``): the small variant (the package's 6 NCRF files
and 1,000-patch bank, downsample 32, ~5 s), its registered ids, the feature-only device layout,
and a generator killed mid-run. Geometry real CAMELYON16, pixels real PCam patches arranged by us."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import shapely

from data_tools.bundle_files.writes import mark_temporary
from data_tools.errors import AnnotationError, BundleError, HistojaxDataError

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = tmp_path_factory.mktemp("c16") / "small"
    make_c16_dataset(out, small=True, progress=False)
    return out


def test_dataset_json_split_labels_scale_and_provenance(small):
    ds = json.loads((small / "dataset.json").read_text())
    assert ds["variant"] == "small" and ds["scale"]["downsample_from_camelyon16_level0"] == 32
    assert ds["scale"]["magnification_range"] == 8  # coarsest level: CAMELYON16 level 0 / 256
    assert "REAL CAMELYON16" in ds["note"] and "NOT A SCANNED SLIDE" in ds["note"]
    for side in ("train", "test"):
        names = [Path(b).name for b in ds[side]]
        assert any(n.startswith("Tumor") for n in names) and any(n.startswith("Normal") for n in names), side
        assert all((small / b / "metadata.json").is_file() for b in ds[side])
    assert not set(ds["train"]) & set(ds["test"])
    by_name = {s["name"]: s for s in ds["slides"]}
    for s in ds["slides"]:  # a borrowed tissue outline stays on its tumour slide's side
        if s["tissue_donor"]:
            side = "test" if f"bundles/{s['name']}" in ds["test"] else "train"
            assert f"bundles/{s['tissue_donor']}" in ds[side]
    assert by_name["Tumor_094"]["finest_views_ge50"] > 0 and by_name["Normal_017"]["finest_views_ge50"] == 0
    assert ds["labels"] == {n: int(n.startswith("Tumor")) for n in by_name}
    assert not list(small.rglob(".*.tmp-*"))


def test_every_tumour_keeps_its_true_size(small):
    """Tumour area on the slide × downsample² equals the CAMELYON16 area (positive minus holes)."""
    from data_tools.annotations import load_annotations
    from data_tools.ncrf import SHIPPED_DIR, read_ncrf

    polygons = read_ncrf(SHIPPED_DIR)
    for name in ("Tumor_072", "Tumor_082", "Tumor_094"):
        true_area = shapely.difference(polygons[name].positive, polygons[name].negative).area
        placed = load_annotations(small / "slides" / f"{name}.geojson").tumour
        assert placed.area * 32**2 == pytest.approx(true_area, rel=0.01), name
        tissue = load_annotations(small / "slides" / f"{name}.geojson").tissue
        assert shapely.difference(placed, tissue).area < 1e-6 * placed.area  # tumour lies on tissue


def test_ids_detection_and_diagnosis(small):
    import histojax

    for env_id, levels in (
        ("HistoJAX-C16-Easy-v0", 3),
        ("HistoJAX-C16-Medium-v0", 5),
        ("HistoJAX-C16-Hard-v0", 7),
        ("HistoJAX-C16-Diagnosis-v0", 5),
    ):
        env, params = histojax.make(env_id, dataset=small, split="test", verify=False)
        assert env.n_levels == levels and params.slide.num_slides == 2
    assert env.task == "classification" and env.num_actions == 9
    labels = dict(zip([b.path.name for b in env.bundles], np.asarray(params.slide.slide_label).tolist()))
    assert labels == {"Tumor_072": 1, "Normal_108": 0}

    @jax.jit
    def declare_tumour(key, params):
        _, state = env.reset(key, params)
        return state.slide_index, env.step(key, state, jnp.int32(8), params)

    index, (obs, state, reward, terminated, *_) = declare_tumour(jax.random.PRNGKey(0), params)
    assert obs.shape == (128, 128, 3) and bool(terminated)
    right = labels[env.bundles[int(index)].path.name] == 1
    assert float(reward) == pytest.approx((1.0 if right else -1.0) - 0.01)


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_detection_draws_tumour_slides_only_and_each_can_succeed(small):
    """Detection ids never start an episode on a normal slide (nothing to find there), the diagnosis id
    draws both kinds, and every tumour slide of the small variant has a finest view >= 50 % tumour (so
    detection can succeed on either side of the split)."""
    import histojax

    ds = json.loads((small / "dataset.json").read_text())
    assert all(s["finest_views_ge50"] > 0 for s in ds["slides"] if s["label"] == 1)
    keys = jax.random.split(jax.random.PRNGKey(1), 256)
    for env_id, kinds in (("HistoJAX-C16-Easy-v0", {1}), ("HistoJAX-C16-Diagnosis-v0", {0, 1})):
        env, params = histojax.make(env_id, dataset=small, split="train", verify=False)
        drawn = np.asarray(jax.vmap(lambda k: env.reset(k, params)[1].slide_index)(keys))
        labels = np.asarray(params.slide.slide_label)
        assert set(labels[np.unique(drawn)].tolist()) == kinds, env_id
    with pytest.raises(ValueError, match="needs a slide with tumour"):
        histojax.make("HistoJAX-C16-Easy-v0", slide=small / "bundles" / "Normal_017", verify=False)


def test_no_dataset_is_a_clear_error(monkeypatch, tmp_path):
    import histojax

    monkeypatch.setenv("HISTOJAX_C16_DATASET", str(tmp_path / "nowhere"))
    with pytest.raises(BundleError, match="python -m data_tools c16 --small --out DIR"):
        histojax.make("HistoJAX-C16-Medium-v0")


def _random_features(bundle: Path, dim: int = 8) -> None:
    """A random feature grid (the device layout does not care what the features mean)."""
    from data_tools.bundle import read_metadata
    from data_tools.features.store import level_grids, save_array, update_metadata

    meta = read_metadata(bundle)
    rng = np.random.default_rng(len(bundle.name))
    levels, written = [], []
    for k, grid in enumerate(level_grids(meta, 128)):
        name = f"features_{k:02d}.npy"
        save_array(bundle / name, rng.standard_normal((*grid, dim)).astype(np.float16))
        levels.append({"file": name, "grid": list(grid)})
        written.append(name)
    update_metadata(
        bundle,
        {
            "encoder": "random-test",
            "encoder_dim": dim,
            "image_size": None,
            "dim": dim,
            "stride": 128,
            "dtype": "float16",
            "projection": None,
            "source": "test",
            "levels": levels,
        },
        written,
    )


def test_feature_mode_holds_no_pixels(small, tmp_path):
    """obs_mode="features": no pixel array on the device, bytes as computed from the metadata, and the
    same tumour fractions (hence rewards) as pixel mode on the same trajectory."""
    import shutil

    import histojax
    from data_tools.bundle import read_metadata
    from data_tools.bundle_files.format import select_levels, slide_device_bytes

    ds = tmp_path / "ds"
    shutil.copytree(small, ds)
    for b in (ds / "bundles").iterdir():
        _random_features(b)
    env_f, params_f = histojax.make(
        "HistoJAX-C16-Medium-v0", dataset=ds, split="train", obs_mode="features", verify=False
    )
    env_p, params_p = histojax.make("HistoJAX-C16-Medium-v0", dataset=ds, split="train", verify=False)
    s = params_f.slide
    assert s.pixels is None and s.tile_pool is None and s.tile_index is None and s.features is not None
    assert params_p.slide.tile_pool is not None
    leaves = sum(int(a.nbytes) for a in jax.tree.leaves(s))
    expected = sum(
        slide_device_bytes(m, select_levels(m, 5), pixels=False, features=True)
        for m in (read_metadata(b.path) for b in env_f.bundles)
    )
    small_arrays = sum(
        int(a.nbytes)
        for a in (
            s.start_logits,
            s.start_cdf,
            s.level_offset,
            s.level_width,
            s.level_height,
            s.downsample,
            s.sat_offset,
            s.tile_offset,
            s.tile_grid_width,
            s.feature_offset,
            s.feature_grid_width,
            s.feature_grid_height,
            s.feature_stride,
            s.slide_label,
            s.slide_logits,
        )
    )
    assert leaves - small_arrays == expected
    assert leaves < sum(int(a.nbytes) for a in jax.tree.leaves(params_p.slide))
    from histojax.core.views import view_tumour_fraction

    rng = np.random.default_rng(0)
    for i in range(12):  # the tumour tables agree with pixel mode's, view by view
        slide = int(rng.integers(2))
        z = int(rng.integers(5))
        w, h = (int(a[slide, z]) for a in (s.level_width, s.level_height))
        x, y = int(rng.integers(w - 127)), int(rng.integers(h - 127))
        args = (jnp.int32(z), jnp.int32(x), jnp.int32(y), 128)
        assert float(view_tumour_fraction(s.select(slide), *args)) == float(
            view_tumour_fraction(params_p.slide.select(slide), *args)
        )
    obs, *_ = jax.jit(lambda k, p: env_f.step(k, env_f.reset(k, p)[1], jnp.int32(4), p))(
        jax.random.PRNGKey(3), params_f
    )
    assert obs.shape == (8,) and obs.dtype == jnp.float32


def test_memory_budget_error_names_what_to_change(small):
    import histojax

    with pytest.raises(BundleError, match="obs_mode='features'"):
        histojax.make("HistoJAX-C16-Hard-v0", dataset=small, max_device_bytes=2**20, verify=False)


# `make test-all`: in `make test` a SIGKILLed build resuming is tests/data_pipeline/test_dataset_command.py::
# test_a_sigkilled_run_resumes (the per-slide step c16 shares) and c16's own leftovers after a kill are
# test_c16_leaves_no_lock_no_partial_features_and_no_stale_temporaries there
@pytest.mark.slow
def test_killed_run_leaves_no_temporaries_and_resumes(small, tmp_path):
    """SIGKILL a generator mid-run; the next run removes what it left and skips the finished slides."""
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = tmp_path / "killed"
    (out / "slides").mkdir(parents=True)
    (out / "bundles").mkdir()
    mark_temporary(out / "bundles" / ".Old.tmp-deadbeef")  # as build_bundle leaves one when killed
    proc = subprocess.Popen(
        [sys.executable, "-m", "data_tools", "c16", "--small", "--quiet", "--out", str(out)],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.time() + 120
        while not (out / "slides" / "Tumor_072.provenance.json").is_file() and time.time() < deadline:
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait()
    first = (out / "slides" / "Tumor_072.tif").stat().st_mtime_ns
    assert not (out / "dataset.json").exists()
    (mark_temporary(out / "slides" / ".Tumor_082.tif.tmp-999999") / "Tumor_082.tif").write_bytes(b"half a tiff")
    ds = make_c16_dataset(out, small=True, progress=False)
    assert (out / "slides" / "Tumor_072.tif").stat().st_mtime_ns == first  # not made again
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob(".*.old-*"))
    assert ds["train"] == json.loads((small / "dataset.json").read_text())["train"]


def test_bad_inputs_name_the_file(tmp_path):
    from data_tools.datasets.c16.dataset import make_c16_dataset
    from data_tools.datasets.pcam_bank import load_bank
    from data_tools.ncrf import read_ncrf

    bad = tmp_path / "ann"
    bad.mkdir()
    (bad / "Tumor_001.json").write_text("{not json")
    with pytest.raises(AnnotationError, match="Tumor_001.json: not valid NCRF JSON"):
        read_ncrf(bad)
    with pytest.raises(AnnotationError, match="no such folder"):
        read_ncrf(tmp_path / "missing.tar.gz")
    (tmp_path / "patches" / "0").mkdir(parents=True)
    with pytest.raises(HistojaxDataError, match="holds no patches labelled 0"):
        load_bank(tmp_path / "patches")
    with pytest.raises(HistojaxDataError, match="--downsample 0.5"):
        make_c16_dataset(tmp_path / "out", small=True, downsample=0.5, progress=False)
    assert not (tmp_path / "out").exists()


def test_shipped_bank_is_small_and_balanced():
    from data_tools.datasets.pcam_bank import SHIPPED_BANK, load_bank

    bank = load_bank()
    assert len(bank) == 1000 and int(bank.labels.sum()) == 500
    assert SHIPPED_BANK.stat().st_size < 6 * 2**20
    assert bank.decode([0]).shape == (1, 96, 96, 3)


@pytest.mark.slow
def test_benchmark_scale_build_of_the_shipped_slides(tmp_path):
    """The six shipped slides at the full benchmark's scale (downsample 8, ~1 min): true tumour sizes,
    micro- and macro-metastases findable at the finest level, and the Hard env over all six."""
    import histojax
    from data_tools.annotations import load_annotations
    from data_tools.datasets.c16.dataset import SMALL_SLIDES, make_c16_dataset
    from data_tools.ncrf import SHIPPED_DIR, read_ncrf

    ds = make_c16_dataset(tmp_path / "d8", names=list(SMALL_SLIDES), progress=False, workers=2)
    assert ds["scale"]["downsample_from_camelyon16_level0"] == 8 and ds["scale"]["magnification_range"] == 32
    polygons = read_ncrf(SHIPPED_DIR)
    for rec in ds["slides"]:
        if rec["label"]:
            placed = load_annotations(tmp_path / "d8" / "slides" / f"{rec['name']}.geojson").tumour
            true = shapely.difference(polygons[rec["name"]].positive, polygons[rec["name"]].negative).area
            assert placed.area * 64 == pytest.approx(true, rel=0.01)
            assert rec["finest_views_ge50"] > 0, rec["name"]
        else:
            assert rec["finest_views_ge50"] == 0
    env, params = histojax.make("HistoJAX-C16-Hard-v0", dataset=tmp_path / "d8", split="all", verify=False)
    assert params.slide.num_slides == 6


def test_pool_features_equal_the_views_they_describe(small, tmp_path):
    """A tiled bundle's feature grid at stride = tile size is computed from the distinct pool tiles (glass
    once); every cell still equals the encoder applied to that cell's view, looked up directly."""
    import shutil

    from data_tools.bundle_files.reading import load_bundle, read_metadata
    from data_tools.features.colour import colour_stats
    from data_tools.features.grid import compute_features

    bundle = tmp_path / "Tumor_082"
    shutil.copytree(small / "bundles" / "Tumor_082", bundle)
    compute_features(bundle, encoder_name="colour-stats", dtype="float32", progress=False, batch=16)
    meta = read_metadata(bundle)
    loaded = load_bundle(bundle)
    t = meta.tile_size
    for k in (0, len(meta.levels) // 2):
        grid = np.load(bundle / meta.features["levels"][k]["file"])
        gh, gw = grid.shape[:2]
        views = np.stack(
            [
                np.asarray(loaded.pixels[k][gy * t : (gy + 1) * t, gx * t : (gx + 1) * t])
                for gy in range(gh)
                for gx in range(gw)
            ]
        )
        direct = np.asarray(colour_stats(jnp.asarray(views))).reshape(gh, gw, -1)
        np.testing.assert_allclose(grid, direct, atol=1e-6)


# `make test-all` (three builds of the set): in `make test` c16 --no-pixels builds the shared small set
# (conftest.py's c16_small, read by tests/data_pipeline/test_folds.py) and the dataset command's --no-pixels path is
# tests/data_pipeline/test_dataset_command.py's, with pixel mode refused by tests/training/test_evaluate_cli.py's no-pixels test
@pytest.mark.slow
def test_feature_only_bundles(small, tmp_path):
    """``--no-pixels``: after the feature grid the RGB pools of every level but the coarsest are deleted; the
    features env is unchanged, pixel mode is refused naming what to do, rendering still works, and the
    same command without the flag brings the pixels back."""
    import shutil

    import histojax
    from data_tools.bundle_files.reading import read_metadata
    from data_tools.datasets.c16.dataset import make_c16_dataset

    out = tmp_path / "ds"
    shutil.copytree(small, out)
    with_pixels = make_c16_dataset(out, small=True, features="colour-stats", progress=False)
    env_a, params_a = histojax.make("HistoJAX-C16-Easy-v0", dataset=out, split="train", obs_mode="features")
    key = jax.random.PRNGKey(5)
    obs_a, state_a = env_a.reset(key, params_a)
    ds = make_c16_dataset(out, small=True, features="colour-stats", no_pixels=True, progress=False)
    assert not ds["pixels_kept"] and ds["encoder"] == "colour-stats"
    assert ds["disk_bytes"]["bundles"] < with_pixels["disk_bytes"]["bundles"] / 2
    assert ds["device_bytes"]["pixels"] == with_pixels["device_bytes"]["pixels"]  # what pixel mode would need
    assert 0 < ds["device_bytes"]["features"] < ds["device_bytes"]["pixels"]
    for b in (out / "bundles").iterdir():
        meta = read_metadata(b)
        assert meta.pixel_levels == [len(meta.levels) - 1]
        assert sorted(p.name for p in b.glob("tiles_*.npy")) == [f"tiles_{len(meta.levels) - 1:02d}.npy"]
    env_b, params_b = histojax.make("HistoJAX-C16-Easy-v0", dataset=out, split="train", obs_mode="features")
    obs_b, state_b = env_b.reset(key, params_b)
    np.testing.assert_array_equal(obs_a, obs_b)
    step = jax.jit(lambda k, s, p: env_b.step(k, s, jnp.int32(4), p))
    np.testing.assert_array_equal(step(key, state_a, params_a)[0], step(key, state_b, params_b)[0])
    with pytest.raises(BundleError, match="--no-pixels"):
        histojax.make("HistoJAX-C16-Easy-v0", dataset=out, split="train")
    from histojax.render import animate, render_trajectory

    z, x, y = (np.asarray([getattr(state_b, f)]) for f in ("z", "x", "y"))
    render_trajectory(env_b, z, x, y, tmp_path / "t.png", slide_index=int(state_b.slide_index))
    animate(env_b, z, x, y, tmp_path / "t.gif", slide_index=int(state_b.slide_index))
    make_c16_dataset(out, small=True, progress=False)  # without the flag: pixels again
    for b in (out / "bundles").iterdir():
        meta = read_metadata(b)
        assert meta.pixel_levels == list(range(len(meta.levels)))
    histojax.make("HistoJAX-C16-Easy-v0", dataset=out, split="train")


def _provenance(folder: Path, name: str) -> dict:
    return json.loads((folder / "slides" / f"{name}.provenance.json").read_text())


def test_train_and_test_slides_share_no_patch(small):
    """Every slide draws its texture from its split's pool only: no patch textures both sides, and each
    side's patches are in that side's pool by the recorded rule."""
    from data_tools.datasets.pcam_bank import in_test_pool

    ds = json.loads((small / "dataset.json").read_text())
    assert ds["format"] == 2 and ds["patch_pools"]["rule"].startswith("test pool iff")
    used = {}
    for side in ("train", "test"):
        names = set()
        for bundle in ds[side]:
            prov = _provenance(small, Path(bundle).name)
            assert prov["patch_pool"] == side
            for lab, patch_names in prov["patch_names"].items():
                names |= {(int(lab), n) for n in patch_names}
        used[side] = names
    assert used["train"] and used["test"] and not used["train"] & used["test"]
    for side, names in used.items():
        labs, pnames = zip(*sorted(names))
        assert (in_test_pool(pnames, labs) == (side == "test")).all(), side


def test_a_subset_keeps_the_whole_sets_split_donor_and_slides(small, tmp_path):
    """`--slides Tumor_072` alone (its donor not named) builds, with the same donor and pixels as the whole
    set, and on the whole set's folder leaves the other slides and the split as they were."""
    import shutil

    from data_tools.datasets.c16.dataset import make_c16_dataset

    whole = json.loads((small / "dataset.json").read_text())
    alone = tmp_path / "alone"
    ds = make_c16_dataset(alone, small=True, names=["Tumor_072"], progress=False)
    assert ds["variant"] == "subset" and ds["test"] == ["bundles/Tumor_072"] and ds["train"] == []
    assert _provenance(alone, "Tumor_072")["settings"] == _provenance(small, "Tumor_072")["settings"]
    assert (alone / "slides" / "Tumor_072.tif").read_bytes() == (small / "slides" / "Tumor_072.tif").read_bytes()
    with pytest.raises(BundleError, match="split of this subset is empty"):
        import histojax

        histojax.make("HistoJAX-C16-Easy-v0", dataset=alone, split="train", obs_mode="features")
    copy = tmp_path / "copy"
    shutil.copytree(small, copy)
    again = make_c16_dataset(copy, small=True, names=["Tumor_072", "Normal_108"], progress=False)
    assert again["variant"] == "small"
    assert (again["train"], again["test"]) == (whole["train"], whole["test"])
    assert [s["name"] for s in again["slides"]] == [s["name"] for s in whole["slides"]]


def test_test_slides_from_another_patch_set(tmp_path):
    """--test-patches: the test slides are textured from that set alone (here: the shipped bank's test pool
    written out as a folder, a stand-in for PCam's own test split)."""
    from data_tools.datasets.c16.dataset import make_c16_dataset
    from data_tools.datasets.pcam_bank import load_bank, split_pools

    _, pool = split_pools(load_bank())
    other = tmp_path / "other"
    for i in range(len(pool)):
        f = other / str(int(pool.labels[i])) / f"x{pool.names[i]}"
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(pool.blob[pool.offsets[i] : pool.offsets[i + 1]].tobytes())
    out = tmp_path / "ds"
    ds = make_c16_dataset(out, small=True, names=["Tumor_072"], test_patches=other, progress=False)
    assert ds["patch_pools"]["test"]["other_patch_set"] and ds["patch_pools"]["test"]["source"] == str(other)
    prov = _provenance(out, "Tumor_072")
    assert all(n.startswith("x") for names in prov["patch_names"].values() for n in names)


def test_v1_ids_need_a_format_2_dataset_with_pcam_cnn_features(small, tmp_path):
    import histojax

    ds = json.loads((small / "dataset.json").read_text())
    ds.pop("dataset_sha256", None)  # a format-1 dataset was written before dataset.json was sealed
    old = tmp_path / "old"
    old.mkdir()
    (old / "dataset.json").write_text(
        json.dumps(
            {
                **ds,
                "format": 1,
                "train": [str(small / b) for b in ds["train"]],
                "test": [str(small / b) for b in ds["test"]],
            }
        )
    )
    with pytest.raises(BundleError, match="format >= 2.*use the -v0 id"):
        histojax.make("HistoJAX-C16-Hard-v1", dataset=old)
    with pytest.raises(BundleError, match="pcam-cnn features, and this dataset records no feature grids"):
        histojax.make("HistoJAX-C16-Hard-v1", dataset=small)


FULL_RECORD = ROOT / "tests" / "data" / "c16_full_patch_names.npz"


@pytest.mark.skipif(
    not FULL_RECORD.is_file(),
    reason="the full set's patch record is made by experiments/c16_patch_record.py after a full build",
)
def test_the_full_sets_sides_share_no_patch():
    """On the recorded patch names of the full true-scale set (239 slides; experiments/c16_patch_record.py):
    no patch textures both a train and a test slide, and each side's patches are in its pool."""
    from data_tools.datasets.pcam_bank import in_test_pool

    rec = np.load(FULL_RECORD)
    train, test = set(rec["train"]), set(rec["test"])
    assert len(train) > 5000 and len(test) > 2000 and list(rec["slides"]) == [180, 59]
    assert not train & test
    for side, keys in (("train", train), ("test", test)):
        labels, names = zip(*(k.split("/", 1) for k in sorted(keys)))
        assert (in_test_pool(names, [int(v) for v in labels]) == (side == "test")).all(), side


# `make test-all` (over a minute on 2 loaded cores): in `make test` the per-slide step it goes through is covered by
# tests/data_pipeline/test_dataset_command.py (test_shards_are_disjoint_and_the_last_writes_dataset_json,
# test_a_bundle_locked_by_another_process_is_skipped, and its failed-slide tests)
@pytest.mark.slow
def test_shards_build_disjoint_slides_and_the_last_writes_dataset_json(small, tmp_path, monkeypatch):
    """`c16 --shard I/N` goes through the dataset command's per-slide step: shard 0/2 builds its half and
    writes no dataset.json; a slide held by another process is skipped (busy); a failing slide is recorded
    with its reason while the rest build; the last shard writes dataset.json (the failure under `failed`,
    exit status 1); `--merge` after a clean rebuild of the failed slide completes the set."""
    from data_tools.datasets.c16 import dataset as c16
    from data_tools.datasets.c16.dataset import SMALL_SLIDES, make_c16_dataset
    from data_tools.datasets.locks import bundle_lock_path, file_lock
    from data_tools.datasets.split import shard_names

    out = tmp_path / "sharded"
    halves = [shard_names(SMALL_SLIDES, (i, 2)) for i in range(2)]
    held = halves[0][0]
    with file_lock(bundle_lock_path(out / "bundles" / held), what="a test"):  # another shard is making it
        first = make_c16_dataset(out, small=True, progress=False, shard=(0, 2))
    assert first["dataset_written"] is False and not (out / "dataset.json").exists()
    assert first["run"]["busy"] == [held] and sorted(first["run"]["built"]) == sorted(halves[0][1:])
    assert sorted(first["missing"]) == sorted(halves[1] + [held])
    assert not (out / "bundles" / held).exists() and not list(out.rglob(".*dataset-lock"))
    made = {n: (out / "slides" / f"{n}.tif").stat().st_mtime_ns for n in halves[0][1:]}

    broken = halves[1][0]
    real = c16.make_bundle

    def failing(out_dir, name, *a, **k):
        if name == broken:
            raise HistojaxDataError(out_dir / "slides" / f"{name}.tif", "a corrupt TIFF (test)")
        return real(out_dir, name, *a, **k)

    monkeypatch.setattr(c16, "make_bundle", failing)
    second = make_c16_dataset(out, small=True, progress=False, shard=(1, 2))
    assert second["dataset_written"] is False and second["missing"] == [held]  # held's shard never made it
    assert "a corrupt TIFF (test)" in second["failed"][broken]
    assert not (out / "bundles" / broken).exists()
    third = make_c16_dataset(out, small=True, progress=False, shard=(0, 2))  # shard 0 again: finishes, writes
    assert third["run"]["built"] == [held] and third["missing"] == []
    written = json.loads((out / "dataset.json").read_text())
    assert written["failed"] == {broken: second["failed"][broken]} and written["variant"] == "subset"
    assert all((out / "slides" / f"{n}.tif").stat().st_mtime_ns == t for n, t in made.items())  # not remade

    monkeypatch.setattr(c16, "make_bundle", real)
    code = subprocess.run(
        [sys.executable, "-m", "data_tools", "c16", "--small", "--quiet", "--out", str(out), "--merge"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert code.returncode == 1 and f"FAILED {broken}: " in code.stderr  # merge builds nothing
    make_c16_dataset(out, small=True, progress=False, shard=(1, 2))  # the failed slide, fixed, is made again
    whole = json.loads((small / "dataset.json").read_text())
    done = json.loads((out / "dataset.json").read_text())
    assert done["failed"] == {} and done["variant"] == "small"
    assert (done["train"], done["test"]) == (whole["train"], whole["test"])
    assert not list(out.rglob(".*.tmp-*")) and not list(out.rglob(".*lock"))
