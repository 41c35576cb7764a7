"""SASHA's reward through the learned attention-MIL head (histojax.reading.head_reward.HeadReward with a
:class:`~histojax.reading.heads.learned.LearnedHead`): the wrapper keeps running sums and adds only the views a
step newly reads (a glimpse cell, a navigator's new finest view); after every step of any trajectory its logit
equals the head rescoring the whole read set from the feature grid, and its rewards equal those of the wrapper
that rescores the whole set every step (``incremental_score=False``).

The tiny synthetic dataset of tests/reading/test_head_reward.py (2 tumour + 2 tumour-free slides, ``colour-stats``
features); the head is drawn at random (its arithmetic, not its skill, is what is tested)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from slide_helpers import synth_feature_dataset

import histojax
from histojax.core import seen_views
from histojax.reading import tables as reading_tables
from histojax.reading.head_reward import HeadReward, pools_views
from histojax.reading.heads.learned import LearnedHead, init_params

STEPS = 12


def _make(dataset, **kw):
    return histojax.make(
        "HistoJAX-Easy-v0",
        dataset=str(dataset),
        split="train",
        obs_mode="features",
        task="classification",
        max_steps_in_episode=STEPS,
        **kw,
    )


def _head(params, seed=0) -> LearnedHead:
    d = int(params.slide.features.shape[-1])
    f = np.asarray(params.slide.features, np.float32).reshape(-1, d)
    p = init_params(jax.random.key(seed), d, hidden=8, attention=4, layers=2, mu=f.mean(0), sd=f.std(0) + 1e-3)
    p["wa"] = p["wa"] * 4.0  # sharp attention: the running maximum moves often
    return LearnedHead(
        params=p,
        cal_a=jnp.float32(1.3),
        cal_b=jnp.float32(-0.2),
        prior_logit=jnp.float32(0.4),
        features_dim=d,
        hidden=8,
        attention=4,
        layers=2,
    )


@pytest.fixture(scope="module")
def setups(tmp_path_factory):
    ds = synth_feature_dataset(tmp_path_factory.mktemp("head-reward-learned"), n_slides=2, negatives=2)
    out = {}
    for name, kw in (("glimpse", dict(action_mode="glimpse:1", step_obs=True, read_budget=0.7)), ("navigator", {})):
        env, params = _make(ds, **kw)
        head = _head(params)
        fast = HeadReward(env, head, gain="fidelity", final=1.0, read_cost=0.01)
        whole = HeadReward(env, head, gain="fidelity", final=1.0, read_cost=0.01, incremental_score=False)
        grids = [
            reading_tables.finest_view_features(s, env.tile_size).astype(np.float32)
            for s, _ in seen_views.per_slide(params, env.bundles)
        ]
        out[name] = dict(
            env=env,
            params=params,
            head=head,
            fast=fast,
            whole=whole,
            grids=grids,
            fast_step=jax.jit(fast.step),
            whole_step=jax.jit(whole.step),
            fast_reset=jax.jit(fast.reset),
            whole_reset=jax.jit(whole.reset),
            rescore=jax.jit(head.score),
        )
    return out


def test_the_learned_head_is_pooled_incrementally(setups):
    for s in setups.values():
        assert pools_views(s["head"]) and s["fast"].pool_incremental and not s["whole"].pool_incremental
        assert s["fast"].tables.terms.shape[-1] == 2


@pytest.mark.slow  # make test-all (keeps make test under 10 min on 2 cores)
@settings(deadline=None, max_examples=6, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(mode=st.sampled_from(["glimpse", "navigator"]), seed=st.integers(0, 2**31 - 1))
def test_incremental_reward_equals_rescoring_the_read_set(setups, mode, seed):
    s = setups[mode]
    env, params, fast = s["env"], s["params"], s["fast"]
    rng = np.random.default_rng(seed)
    key = jax.random.key(seed % 1000)
    obs, st_f = s["fast_reset"](key, params)
    _, st_w = s["whole_reset"](key, params)
    n = env.num_actions
    for t in range(STEPS + 4):
        a = jnp.int32(rng.integers(0, n - 2 if rng.random() < 0.9 else n))  # mostly reads, sometimes a declare
        k = jax.random.fold_in(key, t)
        _, st_f, r_f, term, trunc, info_f = s["fast_step"](k, st_f, a, params)
        _, st_w, r_w, _, _, info_w = s["whole_step"](k, st_w, a, params)
        assert float(r_f) == pytest.approx(float(r_w), abs=2e-4)
        assert int(info_f["head_views"]) == int(info_w["head_views"])
        assert float(info_f["head_score"]) == pytest.approx(float(info_w["head_score"]), abs=1e-4)
        # the running sums against the head rescoring the whole read set from the feature grid
        i = int(st_f.env_state.slide_index)
        g = s["grids"][i]
        mask = np.asarray(fast.read_mask(st_f.env_state, st_f.visited))[: g.shape[0], : g.shape[1]]
        assert int(mask.sum()) == int(st_f.views)
        want = float(s["rescore"](g, mask))
        assert float(st_f.logit) == pytest.approx(want, abs=1e-4)


def test_a_step_reads_only_new_views(setups):
    """Revealing the same glimpse cell twice adds nothing the second time (views and logit unchanged)."""
    s = setups["glimpse"]
    params = s["params"]
    _, st_ = s["fast_reset"](jax.random.key(1), params)
    valid = np.flatnonzero(np.asarray(params.mode_data.valid[int(st_.env_state.slide_index)]))
    a = jnp.int32(valid[0])
    _, st1, _, term, trunc, _ = s["fast_step"](jax.random.key(2), st_, a, params)
    assert int(st1.views) > 0 and not bool(term | trunc)
    _, st2, _, term, trunc, _ = s["fast_step"](jax.random.key(3), st1, a, params)
    assert not bool(term | trunc)
    assert int(st2.views) == int(st1.views) and float(st2.logit) == pytest.approx(float(st1.logit), abs=1e-6)
