"""Training that generalises (validation split, schedules, observation normalisation),
no numpy warnings from windows without episodes, publishing a run and scoring it on any dataset."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from baselines import ppo
from baselines.harness.logs import finite_extreme, finite_mean, load_checkpoint, smooth
from baselines.harness.runner import run_and_save, run_seeds


def test_finite_mean_and_extremes_say_nan_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.isnan(finite_mean([np.nan, np.nan]))
        assert finite_mean([1.0, np.nan, 3.0]) == 2.0
        m = finite_mean(np.array([[np.nan, np.nan], [1.0, np.nan]]), axis=1)
        assert np.isnan(m[0]) and m[1] == 1.0
        assert np.isnan(finite_extreme([np.nan], np.min))
        assert finite_extreme([2.0, np.nan, -1.0], np.min) == -1.0
        assert finite_extreme([2.0, np.nan, -1.0], np.max) == 2.0
        s = smooth(np.array([[np.nan, np.nan, 1.0], [np.nan, 2.0, np.nan]]), 2)
        assert np.isnan(s[0, 0]) and np.isnan(s[0, 1]) and s[0, 2] == 1.0 and s[1, 2] == 2.0


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_tiny_hard_run_where_no_episode_ends_writes_its_logs_without_warnings(tmp_path):
    """Hard with a long step limit and a tiny budget: no episode ends in most windows (the run that
    printed "Mean of empty slice" from the logs and the final window); NaN is recorded instead."""
    config = dict(
        ppo.DEFAULTS,
        env_id="HistoJAX-Hard-v0",
        with_position=True,
        num_envs=2,
        seed=0,
        num_steps=8,
        total_timesteps=64,
        update_epochs=1,
        num_minibatches=2,
        hidden=16,
        num_seeds=2,
        print_progress=True,
        log_every=1,
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        _, _, summary = run_and_save("ppo", ppo.make_train, config, tmp_path / "run")
    assert np.isnan(summary["final"]["steps_to_success"])
    assert (tmp_path / "run" / "log.csv").read_text().count("\n") == 5


# ----------------------------------------------------------------------------- validation split
def _spec():
    """A C16-like dataset.json: 3 tumour slides each lending tissue from a normal slide, 2 lone normals."""
    slides = [{"bundle": f"bundles/T{i}", "label": 1, "tissue_donor": f"N{i}"} for i in range(3)]
    slides += [{"bundle": f"bundles/N{i}", "label": 0, "tissue_donor": None} for i in range(5)]
    return {
        "format": 2,
        "encoder": "pcam-cnn",
        "slides": slides,
        "train": sorted(s["bundle"] for s in slides),
        "test": ["bundles/X"],
    }


def test_validation_split_keeps_donor_pairs_and_both_classes_on_both_sides():
    from baselines.validation import split_train, units

    spec = _spec()
    groups = units(spec)
    assert ["bundles/N0", "bundles/T0"] in groups and ["bundles/N4"] in groups and len(groups) == 5
    for seed in range(5):
        kept, val = split_train(spec, 0.4, seed)
        assert sorted(kept + val) == spec["train"] and not set(kept) & set(val)
        for i in range(3):  # a tumour slide and its tissue donor on the same side
            assert (f"bundles/T{i}" in val) == (f"bundles/N{i}" in val)
        assert any("/T" in b for b in val) and any("/T" in b for b in kept)
    assert split_train(spec, 0.4, 1) == split_train(spec, 0.4, 1)  # seeded
    assert len({tuple(split_train(spec, 0.4, s)[1]) for s in range(8)}) > 1  # the seed matters
    with pytest.raises(ValueError, match="in \\(0, 1\\)"):
        split_train(spec, 0.0)
    with pytest.raises(ValueError, match="at least two"):
        split_train({"train": ["bundles/A"]}, 0.5)


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_validation_dataset_on_the_small_c16_variant(c16_small, tmp_path):
    """The derived dataset loads under the same id: train on its train list, validate on its test list."""
    import histojax
    from baselines.validation import write_validation_dataset

    folder, version = c16_small
    out = write_validation_dataset(folder, 0.2, 0, tmp_path / "val")
    import json

    v = json.loads((out / "dataset.json").read_text())["validation"]
    assert len(v["validation"]) == 2 and len(v["train"]) == 2  # one donor pair held back
    labels = json.loads((folder / "dataset.json").read_text())["labels"]
    assert sorted(labels[n.split("/")[-1]] for n in v["validation"]) == [0, 1]
    env, params = histojax.make(
        f"HistoJAX-C16-Diagnosis-{version}", dataset=out, split="test", obs_mode="features", verify=False
    )
    assert sorted(b.path.name for b in env.bundles) == sorted(n.split("/")[-1] for n in v["validation"])


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_slide_ceiling_pools_view_logits_and_names_the_misses(c16_small, tmp_path):
    """experiments/c16_slide_ceiling.py: AUCs in [0, 1] on both splits, every test tumour slide listed with
    its area, and a dataset without pcam-cnn features refused naming the file."""
    import json

    from experiments import c16_slide_ceiling as ceiling

    folder, version = c16_small
    if version != "v1":
        pytest.skip("pcam-cnn weights not shipped")
    out = tmp_path / "ceiling.json"
    assert ceiling.main(["--dataset", str(folder), "--levels", "0", "1", "--json", str(out)]) == 0
    r = json.loads(out.read_text())
    assert {p["level"] for p in r["pooled"]} == {0, 1}
    assert all(p["test_auc"] is None or 0.0 <= p["test_auc"] <= 1.0 for p in r["pooled"])  # undefined: null
    assert all(p["test_auc"] is None or p["test_auc_low"] <= p["test_auc"] <= p["test_auc_high"] for p in r["pooled"])
    ds = json.loads((folder / "dataset.json").read_text())
    tumour_test = sorted(n.split("/")[-1] for n in ds["test"] if ds["labels"][n.split("/")[-1]])
    assert sorted(t["slide"] for t in r["test_tumour_slides"]) == tumour_test
    assert all(t["tumour_area_mm2"] > 0 for t in r["test_tumour_slides"])
    # the pooling itself: the largest view logit, the mean of the top k, a count above 2
    grid = np.zeros((2, 2, 64), np.float32)
    grid[..., 62] = [[1.0, 3.0], [2.5, -1.0]]
    assert ceiling.pool(grid, 62, "top1") == 3.0 and ceiling.pool(grid, 62, "top3") == pytest.approx(6.5 / 3)
    assert ceiling.pool(grid, 62, "n>2") == 2.0
    bad = tmp_path / "bad"
    bundle = next(folder.glob("bundles/*"))
    (bad / "bundles").mkdir(parents=True)
    import shutil

    shutil.copytree(bundle, bad / "bundles" / bundle.name)
    meta = json.loads((bad / "bundles" / bundle.name / "metadata.json").read_text())
    meta["features"]["encoder"] = "colour-stats"
    (bad / "bundles" / bundle.name / "metadata.json").write_text(json.dumps(meta))
    (bad / "dataset.json").write_text(json.dumps({**ds, "train": [f"bundles/{bundle.name}"], "test": []}))
    with pytest.raises(ceiling.CeilingError, match="metadata.json.*not pcam-cnn"):
        ceiling.slide_grids(bad, "train")


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
# ----------------------------------------------------------------------------- trainer options
def test_entropy_anneal_and_dataset_normaliser(c16_small):
    import jax
    import jax.numpy as jnp

    assert ppo.entropy_coef({"ent_coef": 0.01}, 3, 10) == 0.01
    cfg = {"ent_coef": 0.02, "ent_coef_final": 0.0}
    assert float(ppo.entropy_coef(cfg, 0, 5)) == pytest.approx(0.02)
    assert float(ppo.entropy_coef(cfg, jnp.int32(4), 5)) == pytest.approx(0.0)
    folder, version = c16_small
    config = dict(
        ppo.DEFAULTS,
        env_id=f"HistoJAX-C16-Easy-{version}",
        obs_mode="features",
        with_position=True,
        env_kwargs={"dataset": str(folder), "split": "train", "verify": False},
        num_envs=4,
        num_steps=8,
        total_timesteps=64,
        num_minibatches=2,
        update_epochs=1,
        hidden=16,
        print_progress=False,
        obs_norm="dataset",
        ent_coef_final=0.0,
    )
    train = ppo.make_train(config)
    norm = train.config["obs_norm"]
    feats = np.asarray(train.env_params.slide.features, np.float64)
    d = feats.shape[-1]
    assert len(norm["mean"]) == d and len(norm["std"]) == d and min(norm["std"]) > 0
    out = jax.block_until_ready(run_seeds(train, jax.random.split(jax.random.PRNGKey(0), 1)))
    assert np.isfinite(np.asarray(out["metrics"]["pg_loss"])).all()
    # the network standardises the features: zero-mean inputs for the dataset's mean vector
    from baselines.networks import normalise_features

    x = normalise_features({"features": jnp.asarray([norm["mean"]])}, (tuple(norm["mean"]), tuple(norm["std"])))
    assert np.allclose(np.asarray(x["features"]), 0.0, atol=1e-5)


# ----------------------------------------------------------------------------- publish and evaluate
@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_publish_a_tiny_ppo_and_score_it_on_a_dataset(c16_small, tmp_path):
    import json

    from baselines.evaluate import cli
    from baselines.publish import publish

    folder, version = c16_small
    config = dict(
        ppo.DEFAULTS,
        env_id=f"HistoJAX-C16-Easy-{version}",
        obs_mode="features",
        with_position=True,
        env_kwargs={"dataset": str(folder), "split": "train"},
        num_envs=8,
        num_steps=32,
        total_timesteps=2048,
        num_minibatches=4,
        update_epochs=1,
        hidden=32,
        num_seeds=2,
        seed=0,
        print_progress=False,
    )
    run_and_save("ppo", ppo.make_train, config, tmp_path / "run")
    dest = publish(tmp_path / "run", "tiny-easy", root=tmp_path / "published", seed=1)
    record = json.loads((dest / "published.json").read_text())
    assert record["seeds"] == [1] and record["training_summary"]["seeds"] == 2
    params, cfg = load_checkpoint(dest)
    assert cfg["num_seeds"] == 1 and all(a.shape[0] == 1 for a in __import__("jax").tree.leaves(params))
    assert (
        cli.main(
            [str(dest), "--dataset", str(folder), "--split", "test", "--episodes", "4", "--out", str(tmp_path / "eval")]
        )
        == 0
    )
    rows = json.loads((tmp_path / "eval" / "eval.json").read_text())["results"]
    ((name, table),) = rows.items()
    assert "test split" in name and table["ppo (sampled)"]["episodes"] == 4
    assert "scripted" in table  # the feature-scripted reference runs on feature observations
    with pytest.raises(ValueError, match="not a run folder"):
        publish(tmp_path, "x", root=tmp_path / "published")


def test_published_agents_load_with_their_config():
    """The agents committed in baselines/published/ (navigators chosen on validation slides; the zoom reader,
    trained with defaults on every training slide, by its training success; the cell-set reader, by its
    validation AUC) load with their config, name the C16 id of the version in their name (c16-vN-… → -vN; a v2
    reader may train on the any-dataset id HistoJAX-Reading-v0) and keep one seed of parameters."""
    import json

    import jax

    from baselines.harness.logs import load_checkpoint

    root = Path(__file__).resolve().parents[2] / "baselines" / "published"
    runs = sorted(p for p in root.iterdir() if (p / "params.msgpack").is_file())
    assert {p.name for p in runs} >= {"c16-v1-hard-navigator", "c16-v1-diagnosis"}
    for run in runs:
        params, config = load_checkpoint(run)
        version = run.name.split("-")[1]
        c16_id = config["env_id"].startswith("HistoJAX-C16-") and config["env_id"].endswith(f"-{version}")
        reading_stack = config["env_id"] == "HistoJAX-Reading-v0" and version == "v2"  # the any-dataset id
        assert c16_id or reading_stack, run.name
        assert {jax.tree.leaves(params)[0].shape[0]} == {1}
        record = json.loads((run / "published.json").read_text())
        assert record["chosen_by"]["by"].startswith(("validation", "training success (no validation"))
        assert "test" not in record["chosen_by"]["by"]  # never chosen on the test split
