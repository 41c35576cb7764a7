"""SASHA's reward through a slide head (histojax.reading.head_reward.HeadReward): the reward is the head's score
difference computed by hand from what was read (glimpse cells revealed; a navigator's finest views), the
final diagnosis bonus and the reading cost; vmap of step equals a loop; the same key gives the same
trajectory; the wrapped env's states are the unwrapped env's.

One tiny synthetic dataset (made here: 2 tumour + 2 tumour-free slides of 320 × 256 px, 32-px views,
Easy levels, ``colour-stats`` features; the head reads feature entry 0 as its view logit)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis_examples import examples
from slide_helpers import synth_feature_dataset

import histojax
from histojax.core import seen_views
from histojax.reading import tables as reading_tables
from histojax.reading.head_reward import HeadReward
from histojax.reading.heads import score_logits
from histojax.reading.heads.logit import LogitHead

STEPS, ENVS = 14, 3
HEAD = LogitHead(
    cal_a=jnp.float32(1.5), cal_b=jnp.float32(-0.2), prior_logit=jnp.float32(0.3), dim=0, k=3, top=1, encoder=None
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return synth_feature_dataset(tmp_path_factory.mktemp("head-reward-ds"), n_slides=2, negatives=2)


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


@pytest.fixture(scope="module")
def glimpse(dataset):
    env, params = _make(dataset, action_mode="glimpse:1", step_obs=True, read_budget=0.6)
    return env, params, HeadReward(env, HEAD, gain="log", final=1.0, read_cost=0.05)


@pytest.fixture(scope="module")
def navigation(dataset):
    env, params = _make(dataset)
    return env, params, HeadReward(env, HEAD, gain="prob", final=0.5, read_cost=0.0)


@functools.lru_cache(maxsize=None)
def _jit(fn):
    """``jax.jit(fn)``, one per function for the module: the tests stepping the ``glimpse`` fixture's wrapper compile
    its step once, not once per test (a bound method is the same key while its object lives)."""
    return jax.jit(fn)


def _finest(env, params):
    """Per slide, host: (view logits (H, W), tissue (H, W)) — the head's inputs, straight from the bundles."""
    out = []
    for slide, bundle in seen_views.per_slide(params, env.bundles):
        out.append(
            (
                reading_tables.finest_view_features(slide, env.tile_size)[..., HEAD.dim],
                seen_views.tissue_views(bundle, slide, env.tile_size),
            )
        )
    return out


def _logp(logit, label):
    p = 1.0 / (1.0 + np.exp(-float(logit)))
    return np.log(p if label == 1 else 1.0 - p)


def test_glimpse_reward_is_the_heads_gain_by_hand(glimpse):
    """Each reward = log p(true) after the read − before (masks from the revealed cells, mapped by hand
    through host_tables' instances), + 1 for a right head diagnosis at the end, − 0.05 per cell read."""
    env, params, wrapped = glimpse
    finest = _finest(env, params)
    host = env.action.host_tables(env, params, env.bundles)
    labels = np.asarray(params.slide.slide_label)
    step = _jit(wrapped.step)
    inner_step = jax.jit(env.step_env)
    obs, state = jax.jit(wrapped.reset)(jax.random.key(3), params)
    rng = np.random.default_rng(0)
    c = int(params.mode_data.valid.shape[-1])

    def hand_logit(env_state):
        i = int(env_state.slide_index)
        logits, tissue = finest[i]
        cells = np.flatnonzero(np.asarray(env_state.memory.revealed))
        read = np.isin(host[i]["instance_cell"], cells)
        mask = np.zeros(tissue.size, bool)
        mask[np.flatnonzero(tissue.reshape(-1))[read]] = True
        return float(score_logits(HEAD, jnp.asarray(logits), jnp.asarray(mask.reshape(tissue.shape)))), int(mask.sum())

    seen_read = seen_end = 0
    for t in range(40):
        valid = np.flatnonzero(np.asarray(params.mode_data.valid[int(state.env_state.slide_index)]))
        action = int(rng.choice(valid)) if rng.random() < 0.85 else int(rng.choice([c, c + 1]))
        key = jax.random.key(100 + t)
        before, views_before = hand_logit(state.env_state)
        _, stepped, _, term, trunc, _ = inner_step(key, state.env_state, action, params)
        after, views_after = hand_logit(stepped)
        label = int(labels[int(stepped.slide_index)])
        done = bool(term | trunc)
        expected = _logp(after, label) - _logp(before, label)
        expected += 1.0 if done and ((after >= 0) == (label == 1)) else 0.0
        expected -= 0.05 if views_after > views_before else 0.0
        obs, state, reward, term2, trunc2, info = step(key, state, action, params)
        assert bool(term2 | trunc2) == done
        np.testing.assert_allclose(float(info["head_score"]), after, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(float(reward), expected, rtol=1e-4, atol=1e-4)
        assert int(info["head_views"]) == views_after
        # success: the head right at the episode's end (what evaluate and the trainer's progress call success)
        assert bool(info["success"]) == (done and (after >= 0) == (label == 1)) and "env_success" in info
        seen_read += views_after > views_before
        seen_end += done
        if done:  # a fresh episode: nothing read, the head's prior
            assert float(state.logit) == pytest.approx(float(HEAD.prior_logit)) and int(state.views) == 0
    assert seen_read >= 3 and seen_end >= 2  # the trajectory read cells and ended episodes


def test_fidelity_reward_is_the_gap_to_the_read_everything_score_closed(glimpse):
    """gain="fidelity" (SASHA's label-free reward): each reward = |s_before − s_all| − |s_after − s_all| with
    s_all the head's logit of the whole slide's tissue read, computed by hand; over an episode the rewards sum to
    the gap closed, whatever the slide's label."""
    env, params, _ = glimpse
    wrapped = HeadReward(env, HEAD, gain="fidelity", final=0.0)
    finest = _finest(env, params)
    full = [float(score_logits(HEAD, jnp.asarray(lg), jnp.asarray(ts))) for lg, ts in finest]
    np.testing.assert_allclose(np.asarray(wrapped.tables.full_logit), full, rtol=1e-6, atol=1e-6)
    step = jax.jit(wrapped.step)
    obs, state = jax.jit(wrapped.reset)(jax.random.key(5), params)
    rng = np.random.default_rng(1)
    gained = nonzero = 0
    for t in range(30):
        i = int(state.env_state.slide_index)
        valid = np.flatnonzero(np.asarray(params.mode_data.valid[i]))
        before = float(state.logit)
        obs, new, reward, term, trunc, info = step(jax.random.key(200 + t), state, int(rng.choice(valid)), params)
        after = float(info["head_score"])
        expected = abs(before - full[i]) - abs(after - full[i])
        np.testing.assert_allclose(float(reward), expected, rtol=1e-5, atol=1e-5)
        nonzero += abs(expected) > 1e-6
        gained += expected > 1e-6
        state = new
    assert nonzero >= 3 and gained >= 1  # reads moved the score, some towards the read-everything score


def test_navigator_reads_are_the_finest_views_it_stood_on(navigation):
    """A navigator's head score is the head on the finest views its view stood on (marked by hand)."""
    env, params, wrapped = navigation
    finest = _finest(env, params)
    labels = np.asarray(params.slide.slide_label)
    step = jax.jit(wrapped.step)
    obs, state = jax.jit(wrapped.reset)(jax.random.key(5), params)
    rng = np.random.default_rng(1)
    visited, t_px, f = set(), env.tile_size, env.n_levels - 1
    prev_p = None
    n_finest = 0
    for t in range(60):
        es = state.env_state
        i = int(es.slide_index)
        logits, tissue = finest[i]
        p_before = 1 / (1 + np.exp(-float(state.logit)))
        obs, state, reward, term, trunc, info = step(
            jax.random.key(200 + t), state, int(rng.integers(env.num_actions)), params
        )
        done = bool(term | trunc)
        if not done:  # (after an auto-reset the stepped state is not kept: nothing to compare)
            stepped = state.env_state
            if int(stepped.z) == f:
                gx = min((int(stepped.x) + t_px // 2) // t_px, tissue.shape[1] - 1)
                gy = min((int(stepped.y) + t_px // 2) // t_px, tissue.shape[0] - 1)
                visited.add((gy, gx))
                n_finest += 1
            mask = np.zeros(tissue.shape, bool)
            for gy, gx in visited:
                mask[gy, gx] = True
            mask &= tissue
            expected = float(score_logits(HEAD, jnp.asarray(logits), jnp.asarray(mask)))
            np.testing.assert_allclose(float(info["head_score"]), expected, rtol=1e-5, atol=1e-5)
            label = int(labels[i])
            p_after = 1 / (1 + np.exp(-expected))
            gain = (p_after - p_before) if label == 1 else (p_before - p_after)
            np.testing.assert_allclose(float(reward), gain, rtol=1e-4, atol=1e-5)
        else:
            visited = set()
        prev_p = p_before
    assert prev_p is not None and n_finest >= 3  # the navigator stood on finest views


def test_vmap_equals_a_loop_and_the_key_fixes_the_trajectory(glimpse):
    env, params, wrapped = glimpse
    keys = jax.random.split(jax.random.key(7), ENVS)
    reset_v = jax.jit(jax.vmap(wrapped.reset, in_axes=(0, None)))
    step_v = jax.jit(jax.vmap(wrapped.step, in_axes=(0, 0, 0, None)))
    step_1 = _jit(wrapped.step)
    c = int(params.mode_data.valid.shape[-1])

    def roll(seed):
        obs, st = reset_v(keys, params)
        out = []
        for t in range(10):
            actions = jax.random.randint(jax.random.key(seed * 1000 + t), (ENVS,), 0, c + 2)
            ks = jax.random.split(jax.random.key(50 + t), ENVS)
            singles = [step_1(ks[e], jax.tree.map(lambda a: a[e], st), actions[e], params) for e in range(ENVS)]
            obs, st, r, term, trunc, info = step_v(ks, st, actions, params)
            for e, s in enumerate(singles):
                for a, b in zip(
                    jax.tree.leaves((s[0], s[1], s[2], s[3], s[4], s[5]["head_score"])),
                    jax.tree.leaves(jax.tree.map(lambda x: x[e], (obs, st, r, term, trunc, info["head_score"]))),
                ):
                    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
            out.append((np.asarray(r), np.asarray(st.logit), np.asarray(st.env_state.memory.revealed)))
        return out

    first, again = roll(0), roll(0)
    for a, b in zip(first, again):
        for x, y in zip(a, b):
            np.testing.assert_array_equal(x, y)


def test_wrapped_states_are_the_unwrapped_envs(glimpse):
    """The wrapper auto-resets with the env's own keys: the same actions give the env's own states."""
    env, params, wrapped = glimpse
    c = int(params.mode_data.valid.shape[-1])
    obs_w, st_w = wrapped.reset(jax.random.key(11), params)
    obs_e, st_e = env.reset(jax.random.key(11), params)
    step_w, step_e = _jit(wrapped.step), jax.jit(env.step)
    for t in range(25):
        a = (7 * t + 3) % (c + 2)
        k = jax.random.key(300 + t)
        obs_w, st_w, *_ = step_w(k, st_w, a, params)
        obs_e, st_e, *_ = step_e(k, st_e, a, params)

        # the env's auto-reset leaves the cells-read slots past ``fields`` as they were (they are not the episode's)
        def read(state):
            m = state.memory
            used = jnp.arange(m.slots.shape[-1]) < m.fields
            return state.replace(
                memory=m.replace(
                    slots=jnp.where(used, m.slots, c), slot_summaries=jnp.where(used[:, None], m.slot_summaries, 0)
                )
            )

        for x, y in zip(jax.tree.leaves((obs_w, read(st_w.env_state))), jax.tree.leaves((obs_e, read(st_e)))):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_env_reward_is_added_only_when_asked(glimpse):
    env, params, _ = glimpse
    both = HeadReward(env, HEAD, gain="log", final=1.0, read_cost=0.05, env_reward=True)
    only = HeadReward(env, HEAD, gain="log", final=1.0, read_cost=0.05)
    c = int(params.mode_data.valid.shape[-1])
    _, s1 = both.reset(jax.random.key(1), params)
    _, s2 = only.reset(jax.random.key(1), params)
    _, s3 = env.reset(jax.random.key(1), params)
    for t, a in enumerate([0, 1, c + 1]):
        k = jax.random.key(t)
        _, s1, r1, *_ = both.step(k, s1, a, params)
        _, s2, r2, *_ = only.step(k, s2, a, params)
        _, s3, r3, *_ = env.step(k, s3, a, params)
        assert float(r1) == pytest.approx(float(r2) + float(r3), abs=1e-6)


def test_bad_settings_are_refused(glimpse):
    env, _, _ = glimpse
    with pytest.raises(ValueError, match="gain"):
        HeadReward(env, HEAD, gain="linear")
    with pytest.raises(ValueError, match="read_cost"):
        HeadReward(env, HEAD, read_cost=-1.0)


@pytest.mark.slow  # `make test-all`: builds a PPO navigator and rolls it twice (about a minute on 2 cores)
def test_a_navigators_reads_are_the_finest_tissue_views_of_its_trajectory(dataset, tmp_path):
    """baselines.reading.diagnosis: the read mask of a (freshly initialised) navigator is the set of finest
    tissue views its (sampled) trajectory stood on, recomputed here from the trajectory's (z, x, y)."""
    from baselines import ppo
    from baselines.episodes import policies, rollout
    from baselines.harness.logs import load_checkpoint, save_checkpoint
    from baselines.reading import diagnosis

    config = dict(
        env_id="HistoJAX-Easy-v0",
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
        max_steps_in_episode=30,
        env_kwargs={"dataset": str(dataset), "task": "classification"},
    )
    train = ppo.make_train(config)
    params = train.init_params(jax.random.key(0), train.env_params)
    save_checkpoint(tmp_path / "nav", jax.tree.map(lambda a: a[None], params), train.config)
    reads = diagnosis.navigator_reads(tmp_path / "nav", dataset, "train", seed=0, greedy=False)
    # the same episodes, by hand: the run's env and policy, the finest views on the trajectory
    _, cfg = load_checkpoint(tmp_path / "nav")
    cfg = {**cfg, "env_kwargs": {**cfg["env_kwargs"], "dataset": str(dataset), "split": "train"}}
    cfg, (env, env_params) = rollout.eval_env(cfg)
    net = policies.network_for(cfg, env)
    policy = policies.learned_policy(
        net, params, "discrete", greedy=False, declare=policies.diagnosis_actions(env, net, "discrete")
    )
    n = len(env.bundles)
    per, axes = rollout.per_episode_params(env_params, np.arange(n))
    ep = rollout.run_episodes(env, per, policy, jax.random.key(0), n, params_axes=axes)
    f, t = env.n_levels - 1, env.tile_size
    finest_total = 0
    for e, (slide, bundle) in enumerate(seen_views.per_slide(env_params, env.bundles)):
        tissue = seen_views.tissue_views(bundle, slide, t)
        mask = np.zeros(tissue.shape, bool)
        steps = int(ep["length"][e]) + 1
        for z, x, y in zip(ep["z"][:steps, e], ep["x"][:steps, e], ep["y"][:steps, e]):
            if z == f:
                mask[min((y + t // 2) // t, tissue.shape[0] - 1), min((x + t // 2) // t, tissue.shape[1] - 1)] = True
        expected = np.flatnonzero(mask[tissue])
        finest_total += expected.size
        np.testing.assert_array_equal(np.sort(reads[e]), expected)
    assert finest_total > 0  # the untrained sampled navigator reached the finest level somewhere


@pytest.fixture(
    scope="module", params=[("glimpse:1", 2), ("glimpse:2", 3), ("discrete", 3)], ids=lambda p: f"{p[0]}-k{p[1]}"
)
def incremental_pair(dataset, request):
    """One env (glimpse: read_budget 1, episodes read many cells; a navigator: 60-step episodes) wrapped
    twice, re-scoring the window around each read and scoring the whole grid, and one jitted vmapped
    rollout of both (compiled once)."""
    mode, k = request.param
    if mode == "discrete":
        env, params = histojax.make(
            "HistoJAX-Easy-v0",
            dataset=str(dataset),
            split="train",
            obs_mode="features",
            task="classification",
            max_steps_in_episode=60,
        )
    else:
        env, params = _make(dataset, action_mode=mode, step_obs=True, read_budget=1.0)
    head = HEAD.replace(k=k)
    fast = HeadReward(env, head, gain="fidelity", final=1.0, params=params)
    full = HeadReward(env, head, gain="fidelity", final=1.0, params=params, incremental_score=False)
    assert fast.incremental and not full.incremental
    c = int(params.mode_data.valid.shape[-1]) if mode != "discrete" else 7  # a navigator: actions 0..6, declares 7, 8

    @jax.jit
    def roll(key, actions):  # actions (T, ENVS)
        keys = jax.random.split(key, ENVS)
        outs = []
        for w in (fast, full):
            _, st = jax.vmap(w.reset, in_axes=(0, None))(keys, params)

            def body(st, xs):
                k, a = xs
                _, st, r, term, trunc, info = jax.vmap(w.step, in_axes=(0, 0, 0, None))(
                    jax.random.split(k, ENVS), st, a, params
                )
                return st, (r, st.logit, st.views, info["head_score"], term | trunc)

            outs.append(jax.lax.scan(body, st, (jax.random.split(key, actions.shape[0]), actions))[1])
        return outs

    return roll, c


@settings(max_examples=examples(8, 3), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**31 - 1), declare_rate=st.sampled_from([0.0, 0.05]))
def test_windowed_score_equals_scoring_the_whole_grid(incremental_pair, seed, declare_rate):
    """Re-scoring only the 3 × 3 cells around each revealed cell gives the very floats of scoring the whole
    finest grid: rewards, logits, views read, over episodes with auto-resets (declares end some)."""
    roll, c = incremental_pair
    rng = np.random.default_rng(seed)
    actions = rng.integers(0, c, (40, ENVS))
    actions = np.where(rng.random(actions.shape) < declare_rate, c + rng.integers(0, 2, actions.shape), actions)
    _assert_same_rollouts(*roll(jax.random.key(seed), jnp.asarray(actions, jnp.int32)))


def _assert_same_rollouts(fast, full):
    for name, a, b in zip(("reward", "logit", "views", "head_score", "done"), fast, full):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=name)


def test_windowed_score_equals_scoring_the_whole_grid_on_rollouts_that_read(incremental_pair):
    """The property above on fixed rollouts built to read: a navigator zooms to the finest level first and then
    only pans (no declares), a glimpse reader picks cells; both scorings agree and both read finest tissue."""
    roll, c = incremental_pair
    rng = np.random.default_rng(0)
    if c == 7:  # a navigator: ZOOM_IN twice (Easy: 3 levels), then UP / DOWN / LEFT / RIGHT
        actions = np.concatenate([np.full((2, ENVS), histojax.ZOOM_IN), rng.integers(0, 4, (38, ENVS))])
    else:
        actions = rng.integers(0, c, (40, ENVS))
    fast, full = roll(jax.random.key(0), jnp.asarray(actions, jnp.int32))
    _assert_same_rollouts(fast, full)
    assert np.asarray(full[2]).max() > 0  # the rollouts did read


def test_incremental_score_is_refused_where_it_is_not_exact(glimpse, navigation):
    env, params, _ = glimpse
    with pytest.raises(ValueError, match="incremental_score"):
        HeadReward(env, HEAD.replace(top=3), incremental_score=True)
    nav_env, _, _ = navigation
    with pytest.raises(ValueError, match="incremental_score"):
        HeadReward(nav_env, HEAD.replace(minus_median=True), incremental_score=True)
    assert not HeadReward(env, HEAD.replace(minus_median=True)).incremental
    assert HeadReward(nav_env, HEAD).incremental
