"""Trained policies on the budget curve: a tiny recurrent PPO run (``baselines.ppo_rnn``, a few
hundred steps) in ``glimpse`` mode, and the same GRU policy untrained in ``zoom_select`` mode, is evaluated by ``baselines.reading.budget_curve``
through ``baselines.episodes.rollout.run_episodes``, its GRU state carried through each episode.

One tiny dataset (4 tumour + 4 tumour-free slides of 320 × 256 px, 32-px views, Easy levels, the
``colour-stats`` feature grid) and the two checkpoints, made once for the module."""

from __future__ import annotations

import csv

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from slide_helpers import synth_feature_dataset

from baselines import ppo_rnn
from baselines.common.env import params_initialiser
from baselines.episodes import policies, rollout
from baselines.harness.logs import load_checkpoint, save_checkpoint
from baselines.harness.runner import run_seeds
from baselines.networks import ScannedGRU
from baselines.reading import budget_curve, pipeline

BUDGETS = (0.1, 0.25, 0.5)
STEPS = 8

# The whole module runs under `make test-all`: its fixture compiles the recurrent trainer and two reading rollouts
# (over two minutes on 2 loaded cores before any test). In `make test` the same paths run smaller:
# a recurrent reader evaluated by baselines.episodes.policies.learned_policy / run_episodes
# (tests/reading/test_set_policy.py::test_evaluate_runs_a_set_reader_on_a_wider_slide[True]), the GRU state and the recurrent
# loss (tests/training/test_ppo_rnn.py), a reader's reads scored through a slide head (tests/reading/test_evaluate_readers.py) and
# the readers command's scripted rows (tests/reading/test_head.py::test_readers_command_writes_the_curve).
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return synth_feature_dataset(tmp_path_factory.mktemp("diag-ds"), n_slides=4, negatives=4)


def _config(dataset, action_mode: str) -> dict:
    return dict(
        env_id="HistoJAX-Easy-v0",
        obs="features",
        action_mode=action_mode,
        num_envs=4,
        num_steps=16,
        total_timesteps=256,
        hidden=16,
        num_minibatches=2,
        update_epochs=1,
        num_seeds=1,
        print_progress=False,
        max_steps_in_episode=STEPS,
        env_kwargs={"dataset": str(dataset), "task": "classification", "read_budget": 0.5},
    )


@pytest.fixture(scope="module")
def runs(dataset, tmp_path_factory):
    """A glimpse run trained for 256 steps, and a zoom_select checkpoint of the GRU policy as
    initialised (one compile of the trainer, not two: the reading checks need no training)."""
    root = tmp_path_factory.mktemp("runs")
    train = ppo_rnn.make_train({**_config(dataset, "glimpse:1"), "num_seeds": 3})
    result = jax.block_until_ready(run_seeds(train, jax.random.split(jax.random.PRNGKey(0), 3)))
    save_checkpoint(root / "glimpse", result["params"], train.config)
    zoom = ppo_rnn.make_train(_config(dataset, "zoom_select"))
    init = params_initialiser(
        zoom.env,
        zoom.network,
        1,
        inputs=lambda obs: (
            ScannedGRU.initial_state(1, 16),
            jax.tree.map(lambda a: a[None], obs),
            jnp.ones((1, 1), bool),
        ),
    )
    params = init(jax.random.PRNGKey(1), zoom.env_params)
    save_checkpoint(root / "zoom", jax.tree.map(lambda a: a[None], params), zoom.config)
    return {"glimpse:1": root / "glimpse", "zoom_select": root / "zoom"}


def test_budget_curve_draws_a_recurrent_run(dataset, runs, tmp_path):
    assert load_checkpoint(runs["glimpse:1"])[1]["algo"] == "ppo_rnn"
    assert (
        budget_curve.main(
            [
                "--dataset",
                str(dataset),
                "--env",
                "HistoJAX-Easy-v0",
                "--glimpse-level",
                "1",
                "--budgets",
                *map(str, BUDGETS),
                "--seeds",
                "1",
                "--steps",
                "20",
                "--ppo",
                "GRU glimpse",
                str(runs["glimpse:1"]),
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    with open(tmp_path / "budget_curve.csv") as f:
        rows = list(csv.DictReader(f))
    for name in ("GRU glimpse", "GRU glimpse reader + MIL"):
        mine = [r for r in rows if r["method"] == name]
        assert sorted(float(r["budget"]) for r in mine) == list(BUDGETS), name
        assert all(0.0 <= float(r["auc"]) <= 1.0 and int(r["slides"]) == 3 for r in mine)
        # a trained reader: mean ± std over its 3 seeds, with its fields of view per episode
        assert all(
            int(r["seeds"]) == 3 and float(r["auc_std"]) >= 0 and 0 <= float(r["fields_of_view"]) <= STEPS for r in mine
        )
    random_rows = [r for r in rows if r["method"] == "random reader + MIL"]
    assert random_rows and all(r["fields_of_view"] == "" for r in random_rows)
    assert (tmp_path / "budget_curve.png").stat().st_size > 1000


def test_a_policy_is_scored_by_every_slide_head(dataset, runs):
    """With a max-logit head (pcam-cnn datasets), a policy's reads are scored by it too, beside the MIL."""
    train = pipeline.load_split(dataset, "train", env_id="HistoJAX-Easy-v0", level=1)
    test = pipeline.load_split(dataset, "test", env_id="HistoJAX-Easy-v0", level=1)
    rows = budget_curve.budget_rows(
        (train.tables, train.labels),
        (test.tables, test.labels),
        budgets=(0.5,),
        seeds=1,
        steps=10,
        dataset=dataset,
        policies=[("GRU glimpse", runs["glimpse:1"])],
        policy_seeds=1,
        max_dim=0,
    )
    by = {r["method"]: r for r in rows}
    for name in ("GRU glimpse", "GRU glimpse reader + MIL", "GRU glimpse reader + max logit"):
        assert name in by and 0.0 <= by[name]["auc"] <= 1.0
    assert by["GRU glimpse reader + MIL"]["fraction_read"] == by["GRU glimpse reader + max logit"]["fraction_read"]


@pytest.fixture(scope="module")
def glimpse_reads(dataset, runs):
    return pipeline.policy_reads(runs["glimpse:1"], dataset, "test", BUDGETS)


def test_recurrent_evaluation_respects_the_reading_budget(dataset, runs, glimpse_reads):
    zoom_reads = pipeline.policy_reads(runs["zoom_select"], dataset, "test", BUDGETS)
    tables = pipeline.load_split(dataset, "test", env_id="HistoJAX-Easy-v0", level=1).tables
    for budget in BUDGETS:
        assert len(glimpse_reads[budget]) == len(zoom_reads[budget]) == len(tables)
        for (read, score, fraction, fields), table in zip(glimpse_reads[budget], tables):
            assert fraction <= budget + 1e-6  # glimpse never reads past the budget
            assert 0 <= fields <= STEPS
            assert len(read) == pytest.approx(fraction * table["total"])  # the views read are those counted
            assert 0.0 <= score <= 1.0
        for (read, score, fraction, fields), table in zip(zoom_reads[budget], tables):
            # zoom_select stops once the budget is reached: its last child may add one view
            assert fraction <= budget + 1.0 / table["total"] + 1e-6
            assert len(read) == pytest.approx(fraction * table["total"])
            assert 0.0 <= score <= 1.0


def test_recurrent_evaluation_jit_equals_no_jit(dataset, runs, glimpse_reads):
    with jax.disable_jit():
        plain = pipeline.policy_reads(runs["glimpse:1"], dataset, "test", BUDGETS[-1:])
    for (read, score, fraction, _), (read0, score0, fraction0, _) in zip(
        plain[BUDGETS[-1]], glimpse_reads[BUDGETS[-1]]
    ):
        np.testing.assert_array_equal(read, read0)
        assert score == pytest.approx(score0, abs=1e-5) and fraction == pytest.approx(fraction0, abs=1e-6)


def test_recurrent_policy_carries_its_hidden_state(dataset, runs):
    """The evaluation's own score equals that of a step-by-step rollout carrying the GRU state by hand."""
    from baselines.networks import network_step, preprocess_obs

    params, config = load_checkpoint(runs["glimpse:1"])
    params = jax.tree.map(lambda a: a[0], params)
    config = {**config, "env_kwargs": {**config["env_kwargs"], "split": "test"}}
    _, (env, env_params) = rollout.eval_env(config)
    network = policies.network_for(config, env)
    n = env.num_actions
    policy = policies.learned_policy(network, params, config["action_mode"], True, declare=(n - 2, n - 1))
    slides = np.arange(len(env.bundles))
    per, axes = rollout.per_episode_params(env_params, slides)
    ep = rollout.run_episodes(env, per, policy, jax.random.key(0), len(slides), params_axes=axes, final=True)
    step = jax.jit(
        lambda h, obs: network_step(
            network, params, h, jax.tree.map(lambda a: a[None], preprocess_obs(obs)), jax.numpy.zeros(1, bool)
        )
    )
    reset, env_step = jax.jit(env.reset), jax.jit(env.step)
    for i in slides:
        p = env_params.replace(slide=env_params.slide.replace(slide_logits=per.slide.slide_logits[i]))
        obs, state = reset(jax.random.key(1), p)
        h = ScannedGRU.initial_state(1, network.hidden)
        for _ in range(int(ep["length"][i])):
            h, pi, _ = step(h, obs)
            obs, state, *_ = env_step(jax.random.key(2), state, np.argmax(pi[0]), p)
        own = float(jax.nn.sigmoid(pi[0, n - 1] - pi[0, n - 2]))
        assert own == pytest.approx(float(ep["final_memory"][1][i]), abs=1e-5)


def test_a_policy_read_masks_are_scored_by_the_slide_head(dataset, runs, glimpse_reads):
    """baselines.reading.reader_scores.policy_masks turns a trained reader's reads into finest-level read masks that
    count the same views as the env did, and add_reader scores them with one slide head (histojax.reading.heads.logit)."""
    from baselines.reading import head_fit, reader_scores
    from baselines.reading.slides import load_slides
    from histojax.reading.heads.logit import LogitHead

    slides = load_slides(dataset, "test", dim=0)
    tables = pipeline.load_split(dataset, "test", env_id="HistoJAX-Easy-v0", level=1).tables
    for t, s in zip(tables, slides):  # the env's instances are the tissue views in raster order, as masks count them
        assert t["total"] == s["tissue"].sum()
        np.testing.assert_allclose(t["instances"][:, 0], s["logits"][s["tissue"]], rtol=1e-6)
        pick = np.arange(0, t["total"], 3)
        np.testing.assert_allclose(
            s["logits"][reader_scores.masks_from_instances(s, pick)], t["instances"][pick, 0], rtol=1e-6
        )
    masks = reader_scores.policy_masks(runs["glimpse:1"], dataset, slides, "test", BUDGETS, seeds=1)
    for b in BUDGETS:
        assert len(masks[b]) == 1 and len(masks[b][0]) == len(slides)
        for m, s, (read, _, fraction, _) in zip(masks[b][0], slides, glimpse_reads[b]):
            assert m.shape == s["tissue"].shape and not (m & ~s["tissue"]).any()
            assert m.sum() == len(read) == pytest.approx(fraction * s["tissue"].sum())
    head = head_fit.calibrated(LogitHead(dim=0, k=3, encoder=None), load_slides(dataset, "train", dim=0))
    res = reader_scores.add_reader(reader_scores.new_results(), head, slides, "GRU glimpse", masks)
    rows = reader_scores.rows_from_results(res, slides)
    assert [r["budget"] for r in rows] == list(BUDGETS) and all(r["kind"] == "learned" for r in rows)
    for r in rows:
        want = np.mean([read.size / s["tissue"].sum() for (read, *_), s in zip(glimpse_reads[r["budget"]], slides)])
        assert r["fraction_read"] == pytest.approx(want)
        assert np.isnan(r["auc"]) if len({s["label"] for s in slides}) < 2 else 0.0 <= r["auc"] <= 1.0


def test_readers_command_adds_a_trained_reader(dataset, runs, tmp_path):
    """`python -m baselines.reading.readers --reader NAME RUN`: the trained reader's rows beside the scripted ones,
    scored by the same head (here on the training split, which holds both classes: the policy's own slides, so
    scored only with --allow-fitting-slides, and marked so in readers.csv)."""
    from baselines.reading import head_fit, readers
    from baselines.reading.slides import load_slides
    from histojax.reading.heads.logit import LogitHead

    head_fit.calibrated(LogitHead(dim=0, k=3, encoder=None), load_slides(dataset, "train", dim=0)).save(
        tmp_path / "head"
    )
    assert (
        readers.main(
            [
                "--dataset",
                str(dataset),
                "--head",
                str(tmp_path / "head"),
                "--split",
                "train",
                "--budgets",
                "0.25",
                "0.5",
                "--seeds",
                "1",
                "--reader",
                "GRU glimpse",
                str(runs["glimpse:1"]),
                "--policy-seeds",
                "2",
                "--allow-fitting-slides",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    with open(tmp_path / "out" / "readers.csv") as f:
        rows = list(csv.DictReader(f))
    assert all("policy GRU glimpse:" in r["scored_on_seen_slides"] for r in rows)
    mine = [r for r in rows if r["reader"] == "GRU glimpse"]
    assert sorted(float(r["budget"]) for r in mine) == [0.25, 0.5]
    assert all(
        r["kind"] == "learned" and int(r["seeds"]) == 2 and float(r["fraction_max"]) <= float(r["budget"]) for r in mine
    )
    assert {r["reader"] for r in rows} >= {
        "overview only",
        "random reader",
        "logit reader",
        "search reader",
        "read everything",
    }


def test_a_policy_through_a_learned_head_scores_as_in_the_readers(dataset, runs):
    """One scoring path for trained readers too: the curve's ``NAME reader + learned head`` rows (its reads scored by
    the readers' code, ``reader_slides``) equal the readers' ``--reader NAME RUN`` rows, to the last digit."""
    from test_budget_curve import planted_head

    from baselines.reading import reader_scores

    test = pipeline.load_split(dataset, "test", env_id="HistoJAX-Easy-v0", level=1)
    d = int(test.tables[0]["instances"].shape[1])
    head = planted_head(np.eye(d)[0]).replace(prior_logit=jnp.float32(0.3))  # not the score of a zero view
    level = budget_curve.glimpse_bundle_level(dataset, "HistoJAX-Easy-v0", 1, "test")[0]
    mine = pipeline.load_split(dataset, "test", head=head, cell_level=level)
    curve = budget_curve.policy_rows(
        runs["glimpse:1"],
        dataset,
        "GRU",
        {"learned head": head},
        test.tables,
        test.labels,
        BUDGETS,
        policy_seeds=2,
        reader_slides=mine.slides,
    )
    curve = {r["budget"]: r for r in curve if r["method"] == "GRU reader + learned head"}
    masks = reader_scores.policy_masks(runs["glimpse:1"], dataset, mine.slides, "test", BUDGETS, seeds=2)
    theirs = {
        r["budget"]: r
        for r in reader_scores.rows_from_results(
            reader_scores.add_reader({}, head, mine.slides, "GRU", masks), mine.slides
        )
    }
    assert sorted(curve) == sorted(theirs) == list(BUDGETS)
    for b in BUDGETS:
        for field in ("auc", "auc_std", "auc_low", "auc_high", "accuracy", "seeds"):
            assert curve[b][field] == theirs[b][field], (b, field)
        assert curve[b]["fraction_read"] == pytest.approx(theirs[b]["fraction_read"])
