"""Any slide head through the one protocol (histojax.reading.heads.load), the learned head included: the navigator's
diagnosis (baselines.reading.diagnosis, experiments.navigator_ceiling through the shared score_split /
write_results) and ``histojax evaluate``'s head rows, whose reading maps show the head's per-view scores beside where
the agent read. On the small TRIDENT-layout cohort of tests/learned_fixture.py (no entry is "the logit"), with a
learned head whose instance embedding looks along the planted tumour direction (built here, not fitted)."""

from __future__ import annotations

import csv
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from learned_fixture import make_cohort

from baselines.evaluate.heads import check_head_features, encoder_family
from histojax.reading.heads.learned import LearnedHead, init_params
from histojax.reading.heads.logit import LogitHead

DIM = 16


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    root = tmp_path_factory.mktemp("any-head")
    c = make_cohort(root / "ds", tumour=6, normal=6, test_tumour=2, test_normal=2, dim=DIM, signal=4.0, seed=0)
    p = init_params(jax.random.PRNGKey(0), DIM, 4, 4, 1)
    w1 = np.zeros((DIM, 4), np.float32)
    w1[:, 0] = c["direction"]  # unit 0 reads the planted tumour direction
    p.update(w1=jnp.asarray(w1), wc=jnp.asarray([3.0, 0.0, 0.0, 0.0]), bc=jnp.float32(-3.0))
    head = LearnedHead(params=p, features_dim=DIM, hidden=4, attention=4, layers=1, encoder="imported:s00_tumour.h5")
    head.save(root / "head")
    return {**c, "head": root / "head", "tmp": root}


def _rows(path):
    with open(path) as f:
        return {r["reader"]: r for r in csv.DictReader(f)}


def test_head_features_check_reads_any_head():
    learned = LearnedHead(
        params=init_params(jax.random.PRNGKey(0), 8, 4, 4, 1),
        features_dim=8,
        hidden=4,
        attention=4,
        encoder="imported:a.h5",
    )
    check_head_features(learned, ["imported:b.h5", "imported:c.h5"], 8)  # imported features: one family
    assert encoder_family("imported:x.h5") == encoder_family("imported:y.h5") == "imported"
    with pytest.raises(ValueError, match="reads 8-d feature vectors; these slides' features have 64 entries"):
        check_head_features(learned, ["imported:b.h5"], 64)
    with pytest.raises(ValueError, match="for imported:a.h5 features; these slides hold pcam-cnn"):
        check_head_features(learned, ["pcam-cnn"], 8)
    logit = LogitHead(dim=62, k=2, top=1, encoder="pcam-cnn")
    check_head_features(logit, ["pcam-cnn"], 64)
    with pytest.raises(ValueError, match="reads feature entry 62"):
        check_head_features(logit, ["pcam-cnn"], 16)


def test_navigator_ceiling_scores_through_a_learned_head(cohort, tmp_path, capsys):
    """experiments.navigator_ceiling through the shared scoring loop: the learned head's score reader (no logit
    reader: no entry is a logit), each reader at the per-slide ceiling; the planted signal found reading everything."""
    from experiments import navigator_ceiling

    out = tmp_path / "ceiling"
    assert (
        navigator_ceiling.main(
            [
                "--dataset",
                str(cohort["root"]),
                "--head",
                str(cohort["head"]),
                "--split",
                "test",
                "--max-steps",
                "10000",
                "--budgets",
                "0.2",
                "--seeds",
                "2",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    rows = _rows(out / "readers.csv")
    assert "score reader, per-slide ceiling" in rows and "logit reader, per-slide ceiling" not in rows
    assert float(rows["read everything"]["auc"]) == 1.0  # 2 + 2 test slides, the head looks along the planted direction
    assert json.loads((out / "ceiling.json").read_text())["rows"]


def test_one_class_split_is_refused_by_the_shared_loop(cohort, tmp_path, capsys):
    from baselines.reading import diagnosis

    spec = json.loads((cohort["root"] / "dataset.json").read_text())
    spec["test"] = [e for e in spec["test"] if "tumour" in e]
    (cohort["tmp"] / "one").mkdir()
    one = cohort["tmp"] / "one" / "ds"
    import shutil

    shutil.copytree(cohort["root"], one)
    (one / "dataset.json").write_text(json.dumps(spec))
    out = tmp_path / "diag"
    assert (
        diagnosis.main(
            ["--dataset", str(one), "--head", str(cohort["head"]), "--navigator", "n", str(tmp_path), "--out", str(out)]
        )
        == 2
    )
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "loaded" not in line]
    assert len(err) == 1 and "undefined: one class" in err[0] and "dataset.json" in err[0], err
    assert not out.exists()


@pytest.fixture(scope="module")
def navigator(cohort):
    """A freshly initialised PPO navigator (discrete mode) on the cohort's 3-level bundles."""
    from baselines import ppo
    from baselines.harness.logs import save_checkpoint

    config = dict(
        env_id="HistoJAX-Reading-v0",
        obs_mode="features",
        action_mode="discrete",
        num_envs=2,
        num_steps=4,
        total_timesteps=8,
        hidden=8,
        num_minibatches=1,
        update_epochs=1,
        num_seeds=1,
        print_progress=False,
        max_steps_in_episode=20,
        env_kwargs={"dataset": str(cohort["root"]), "split": "train", "n_levels": 3},
    )
    train = ppo.make_train(config)
    params = train.init_params(jax.random.key(0), train.env_params)
    run = cohort["tmp"] / "nav"
    save_checkpoint(run, jax.tree.map(lambda a: a[None], params), train.config)
    return run


@pytest.mark.slow  # a PPO init and three rollouts compiled (~1 min on 2 cores)
def test_evaluate_and_diagnosis_through_a_learned_head(cohort, navigator, tmp_path, capsys):
    """Was: ``histojax evaluate RUN --head LEARNED`` raised AttributeError ('LearnedHead' has no 'dim'). Now the head
    declares, the AUC is of its scores, and every reading map holds the head's per-view scores beside the reading
    map (a wider picture than the map alone); the diagnosis scores the navigator's reads through it."""
    from PIL import Image

    from baselines.evaluate.cli import main as evaluate_main
    from baselines.reading import diagnosis

    out = tmp_path / "eval"
    assert (
        evaluate_main(
            [
                str(navigator),
                "--dataset",
                str(cohort["root"]),
                "--split",
                "test",
                "--head",
                str(cohort["head"]),
                "--episodes",
                "4",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    record = json.loads((out / "eval.json").read_text())
    assert record["head"]["name"].startswith("learned attention-MIL")
    rows = next(iter(record["results"].values()))
    assert all(r["diagnosis_auc"] is not None for r in rows.values())
    for policy in ("ppo_greedy", "random"):
        for word in ("tumour", "normal"):
            with Image.open(out / f"reading_{policy}_{word}.png") as im:
                w, h = im.size
            assert w > 1.6 * h  # the reading map and the per-view score panel side by side
    d_out = tmp_path / "diag"
    assert (
        diagnosis.main(
            [
                "--dataset",
                str(cohort["root"]),
                "--head",
                str(cohort["head"]),
                "--split",
                "test",
                "--navigator",
                "nav",
                str(navigator),
                "--seeds",
                "2",
                "--out",
                str(d_out),
            ]
        )
        == 0
    )
    rows = _rows(d_out / "readers.csv")
    assert "nav (head declares)" in rows and "score reader" in rows
    assert json.loads((d_out / "readers.json").read_text())["head_kind"] == "learned-attention-mil"


def test_a_detection_policy_scored_through_a_head_keeps_the_dataset_labels(cohort):
    """A cohort labelled by its table with no tumour annotated (the TCGA case): a detection env's bundles make every
    slide normal, so through a head the dataset's own labels are the ones scored (the head's AUC is defined)."""
    import histojax
    from baselines.evaluate.checks import one_class
    from baselines.evaluate.heads import dataset_labelled, refuse_one_class
    from data_tools.errors import HistojaxDataError

    kwargs = {"dataset": str(cohort["root"]), "split": "test"}
    env, params = histojax.make("HistoJAX-Easy-v0", obs_mode="features", **kwargs)
    assert one_class(params) == 0  # the bundles alone: no tumour annotated anywhere
    config = {"env_id": "HistoJAX-Easy-v0", "obs_mode": "features", "env_kwargs": kwargs}
    with pytest.raises(HistojaxDataError, match="only normal"):
        refuse_one_class(config, params)
    labelled = dataset_labelled(env, params, config)
    want = [1 if "tumour" in name else 0 for name in cohort["names"]["test"]]
    assert np.asarray(labelled.slide.slide_label).tolist() == want
    refuse_one_class(config, labelled)  # both classes: scored
    assert dataset_labelled(env, params, config, slide="one.bundle") is params  # one given slide: its own label
