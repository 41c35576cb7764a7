"""Datasets larger than device memory: PPO with K slides resident, rotated between phases
(``baselines.rotation``).

The dataset (8 small slides, ``small_slides``) is more than 3 times the device budget; the run
keeps K=1 slide resident (two sets, the training one and the prefetched next, fit the budget),
reads each set's bundle from disk while the previous set trains, and rotates after every update
(8 phases: every slide trains once). Measured during the run, at each rotation's peak (both sets
on the device): the bytes of the resident sets' buffers, and the bytes of *every* live jax array
on the device — which must not exceed what was there before the first set (the trainer's own
arrays), the train state and the budget: a third set, or the whole dataset, would not fit.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

from baselines import rotation

CONFIG = dict(
    env_id="HistoJAX-Easy-v0",
    num_envs=4,
    num_steps=8,
    total_timesteps=8 * 32,
    update_epochs=1,
    num_minibatches=2,
    hidden=16,
    num_seeds=1,
    print_progress=False,
)


@pytest.fixture(scope="module")
def store(small_slides):
    return rotation.SlideStore("HistoJAX-Easy-v0", small_slides, source="memory")


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
def test_rotating_run_stays_under_the_device_budget(small_slides, store):
    dataset = store.nbytes()
    budget = dataset // 3
    result = rotation.train_rotating(
        {**CONFIG, "env_kwargs": {"slides": small_slides}},
        budget_bytes=budget,
        resident=None,
        rotate_every=1,
        source="disk",
    )
    rot = result["rotation"]
    assert rot["dataset_bytes"] == dataset >= 3 * budget
    assert rot["resident_slides"] == 1  # the most that fit twice in a third of the dataset
    assert rot["phases"] == 8 and sorted(i for s in rot["sets"] for i in s) == list(range(8))
    assert rot["resident_peak_bytes"] == rot["bound_bytes"] <= budget  # two sets at the peak, never more
    assert rot["live_peak_bytes"] <= rot["baseline_bytes"] + rot["train_state_bytes"] + budget, rot
    assert rot["live_peak_bytes"] >= rot["baseline_bytes"] + rot["bound_bytes"]  # the measure sees both sets
    for name in ("pg_loss", "v_loss", "entropy"):
        assert result["metrics"][name].shape == (1, 8) and np.isfinite(result["metrics"][name]).all(), name
    assert all(np.isfinite(np.asarray(a)).all() for a in jax.tree.leaves(result["params"]))


def test_sets_capacity_and_budget_errors(store):
    sets = rotation.plan_sets(8, 3, seed=0)
    assert len(sets) == 3 and all(len(s) == 3 for s in sets)
    assert sorted(set(i for s in sets for i in s)) == list(range(8))
    cap = rotation.capacity(store, sets)
    assert cap["slide_logits"] == (3,) and cap["level_width"] == (3, 3)
    rows = max(sum(store.shapes[i]["pixels"][0] for i in s) for s in sets)
    assert cap["pixels"] == (rows, 3)
    # every set packs to exactly the capacity: one compiled program for all
    for s in sets:
        packed = rotation.build_set(store, s, cap, jax.devices()[0])
        assert {k: v.shape for k, v in rotation.host_leaves(packed).items()} == cap
        assert rotation.tree_bytes(packed) == rotation.capacity_bytes(store, cap)
    k, _, _, set_bytes = rotation.choose_resident(store, budget_bytes=10**12, k=None)
    assert k == 8 and 2 * set_bytes <= 10**12
    with pytest.raises(ValueError, match="more than the budget of 1,000"):
        rotation.choose_resident(store, budget_bytes=1000, k=None)
    with pytest.raises(ValueError, match="between 1 and the dataset's 8 slides"):
        rotation.plan_sets(8, 9)
    with pytest.raises(ValueError, match="one device"):
        rotation.train_rotating({**CONFIG, "devices": 2}, budget_bytes=10**9)
