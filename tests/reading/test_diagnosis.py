"""Reading modes (``glimpse``, ``zoom_select``), the reading memory, the score and the efficiency
metrics, and the AUC of the diagnosis benchmark.

One small slide (1024 × 768 px, 32-px views, 3 levels at downsamples 16, 4, 1; glimpse cells at
the middle level: 6 × 8 cells of 4 × 4 finest views) with the cheap
``colour-stats`` feature grid; one jitted rollout per mode, compiled once for the module."""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import histojax
from histojax.reading.modes.glimpse import Glimpse, observation_bytes, with_budget
from histojax.reading.modes.zoom_select import ZoomSelect

TILE, STEPS = 32, 12


@pytest.fixture(scope="module")
def bundle(tmp_path_factory) -> Path:
    from slide_helpers import tiny_feature_bundle

    return tiny_feature_bundle(tmp_path_factory.mktemp("diag"), seed=1, tile=TILE)


@pytest.fixture(scope="module")
def glimpse(bundle):
    return histojax.make(
        "HistoJAX-Easy-v0",
        slide=bundle,
        obs_mode="features",
        action_mode=Glimpse(level=1),
        task="classification",
        max_steps_in_episode=STEPS,
        auto_reset=False,
    )


@pytest.fixture(scope="module")
def zoom(bundle):
    return histojax.make(
        "HistoJAX-Easy-v0",
        slide=bundle,
        action_mode="zoom_select",
        task="classification",
        max_steps_in_episode=STEPS,
        auto_reset=False,
    )


def _rollout(env):
    """``rollout(key, actions, params) → (states, infos, obs)`` stacked over the steps (one program)."""

    def rollout(key, actions, params):
        obs, state = env.reset(key, params)

        def body(carry, a):
            state, key = carry
            key, sub = jax.random.split(key)
            obs, state, _, _, _, info = env.step(sub, state, a, params)
            return (state, key), (state, info, obs)

        return jax.lax.scan(body, (state, key), actions)[1]

    return rollout


@pytest.fixture(scope="module")
def glimpse_rollout(glimpse):
    return jax.jit(_rollout(glimpse[0]))


@pytest.fixture(scope="module")
def zoom_rollout(zoom):
    return jax.jit(_rollout(zoom[0]))


def _equal(a, b):
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


# glimpse in `make test`, zoom_select under `make test-all` (for zoom_select in `make test`: test_zoom_select_children,
# test_zoom_select_counts_finest_views_read here and tests/reading/test_reading_auto_reset.py::test_vmap_equals_loop[zoom_runs])
ZOOM_SLOW = pytest.param("zoom", marks=pytest.mark.slow)


@pytest.mark.parametrize("which", ["glimpse", ZOOM_SLOW])
def test_jit_equals_no_jit(which, request):
    env, params = request.getfixturevalue(which)
    rollout = request.getfixturevalue(f"{which}_rollout")
    n = env.num_actions - 2  # no diagnosis: the whole episode runs
    actions = jax.random.randint(jax.random.key(3), (STEPS - 1,), 0, n)
    jitted = rollout(jax.random.key(7), actions, params)
    with jax.disable_jit():
        plain = _rollout(env)(jax.random.key(7), actions, params)
    _equal(jitted, plain)


@pytest.mark.parametrize("which", ["glimpse", ZOOM_SLOW])
def test_vmap_equals_loop(which, request):
    env, params = request.getfixturevalue(which)
    rollout = request.getfixturevalue(f"{which}_rollout")
    keys = jax.random.split(jax.random.key(11), 3)
    actions = jax.random.randint(jax.random.key(5), (3, STEPS - 1), 0, env.num_actions)
    batched = jax.jit(jax.vmap(_rollout(env), in_axes=(0, 0, None)))(keys, actions, params)
    for i in range(3):
        _equal(jax.tree.map(lambda x: x[i], batched), rollout(keys[i], actions[i], params))


def _direct_tables(bundle):
    """Tissue views and the mean ‖ max of their features per glimpse cell, from the bundle's files
    (finest level first; the glimpse grid is the middle level's, downsample 4; tissue at 1/16)."""
    from data_tools.bundle import load_bundle, read_metadata

    b = load_bundle(bundle, verify=False)
    meta = read_metadata(bundle)
    finest = np.load(bundle / meta["features"]["levels"][0]["file"])  # (gh, gw, D) at 32-px stride
    coarse = np.load(bundle / meta["features"]["levels"][1]["file"])  # the glimpse cells' own features
    ratio = round(meta["levels"][1]["downsample"] / meta["levels"][0]["downsample"])  # 4 finest px per cell-level px
    mask = round(meta["levels"][-1]["downsample"])
    assert b.tissue.shape[1] * mask == b.pixels[0].shape[1]  # the tissue mask is at the coarsest level
    tissue_full = np.kron(b.tissue.astype(float), np.ones((mask, mask)))
    gh, gw = finest.shape[:2]
    frac = tissue_full[: gh * TILE, : gw * TILE].reshape(gh, TILE, gw, TILE).mean(axis=(1, 3))
    tissue = frac >= 0.25
    cgh, cgw = coarse.shape[:2]
    cells = {}
    for gy in range(cgh):
        for gx in range(cgw):
            # finest views whose centre falls in the cell's footprint (px of the finest level; last row/col take the rest)
            cx = (np.arange(gw) + 0.5) * TILE
            cy = (np.arange(gh) + 0.5) * TILE
            in_x = (cx >= gx * TILE * ratio) & ((cx < (gx + 1) * TILE * ratio) | (gx == cgw - 1))
            in_y = (cy >= gy * TILE * ratio) & ((cy < (gy + 1) * TILE * ratio) | (gy == cgh - 1))
            under = in_y[:, None] & in_x[None, :] & tissue
            cells[gy * cgw + gx] = (int(under.sum()), finest[under])
    return cells, int(tissue.sum()), coarse.reshape(cgh * cgw, -1)


def test_revealed_content_equals_a_direct_lookup(glimpse, bundle):
    env, params = glimpse
    cells, total, low = _direct_tables(bundle)
    np.testing.assert_allclose(np.asarray(params.mode_data.cells[0]), low, rtol=1e-6)
    assert int(params.mode_data.total_views[0]) == total
    obs, state = env.reset(jax.random.key(0), params)
    step = jax.jit(env.step)
    order = [c for c, (n, _) in cells.items() if n > 0]
    read = 0
    for c in order:
        obs, state, _, _, truncated, info = step(jax.random.key(c), state, c, params)
        n, feats = cells[c]
        read += n
        np.testing.assert_allclose(
            np.asarray(obs["summaries"][c]), np.concatenate([feats.mean(0), feats.max(0)]), rtol=1e-5, atol=1e-6
        )
        assert float(obs["revealed"][c]) == 1.0
        assert float(info["fraction_read"]) == pytest.approx(read / total)
    assert bool(truncated)  # the whole slide read: the (full) budget is spent
    assert int(info["fields_of_view"]) == len(order)
    # the observation is as large as stated
    assert observation_bytes(env, params) == sum(np.asarray(v).nbytes for v in obs.values())


def test_glimpse_grid_pins_the_spaces_to_another_dataset(glimpse, bundle):
    """``glimpse_grid``: the cells padded to a given grid (a policy trained elsewhere fits), the same
    reading of every real cell; a slide too large for it refused naming the bundle; the trainers record
    the grid of their slides in the config they save."""
    from baselines.common.env import pin_env_shapes

    env, params = glimpse
    h, w = (int(v) for v in np.asarray(params.mode_data.grid))
    assert h * w == params.mode_data.valid.shape[-1]
    big_env, big = histojax.make(
        "HistoJAX-Easy-v0",
        slide=bundle,
        obs_mode="features",
        action_mode=Glimpse(level=1),
        task="classification",
        max_steps_in_episode=STEPS,
        auto_reset=False,
        glimpse_grid=(h + 1, w + 2),
    )
    assert big_env.num_actions == (h + 1) * (w + 2) + 2
    assert big_env.observation_space(big)["cells"].shape[0] == (h + 1) * (w + 2)
    small_cells = np.asarray(params.mode_data.cells[0]).reshape(h, w, -1)
    big_cells = np.asarray(big.mode_data.cells[0]).reshape(h + 1, w + 2, -1)
    np.testing.assert_array_equal(big_cells[:h, :w], small_cells)
    assert not np.asarray(big.mode_data.valid[0]).reshape(h + 1, w + 2)[h:, :].any()
    with pytest.raises(ValueError, match=f"{bundle.name}.*do not fit glimpse_grid"):
        histojax.make(
            "HistoJAX-Easy-v0",
            slide=bundle,
            obs_mode="features",
            action_mode=Glimpse(level=1),
            task="classification",
            glimpse_grid=(h - 1, w),
        )
    config = pin_env_shapes({"env_kwargs": {"read_budget": 0.5}}, params)
    assert config["env_kwargs"] == {"read_budget": 0.5, "glimpse_grid": [h, w]}
    _, zoom_params = histojax.make("HistoJAX-Easy-v0", slide=bundle, action_mode="zoom_select", task="classification")
    assert pin_env_shapes({"a": 1}, zoom_params) == {"a": 1}


def test_repicking_reveals_nothing_new(glimpse):
    env, params = glimpse
    _, state = env.reset(jax.random.key(0), params)
    c = int(np.flatnonzero(np.asarray(params.mode_data.valid[0]))[0])
    obs1, state1, *_, info1 = env.step(jax.random.key(1), state, c, params)
    obs2, state2, *_, info2 = env.step(jax.random.key(2), state1, c, params)
    _equal((obs1, state1.memory), (obs2, state2.memory))
    assert int(info2["fields_of_view"]) == 1 and int(info2["steps"]) == 2


@settings(deadline=None, max_examples=25)
@given(budget=st.sampled_from([0.05, 0.1, 0.2, 0.5, 1.0]), seed=st.integers(0, 2**16))
def test_reading_budget_is_respected(glimpse, glimpse_rollout, budget, seed):
    env, params = glimpse
    params = with_budget(params, budget)
    actions = jax.random.randint(jax.random.key(seed), (STEPS - 1,), 0, env.num_actions - 2)
    states, infos, obs = glimpse_rollout(jax.random.key(seed), actions, params)
    fraction = np.asarray(infos["fraction_read"])
    assert np.all(fraction <= budget + 1e-6)
    assert np.all(np.diff(fraction) >= 0)
    ended = np.asarray(infos["truncated"])
    if ended.any():  # the episode ends at the budget (or the step limit) and reads nothing after
        first = int(np.argmax(ended))
        assert (
            first == STEPS - 2
            or bool(states.memory.over_budget[first])
            or fraction[first]
            >= np.floor(budget * int(params.mode_data.total_views[0]) + 1e-4) / int(params.mode_data.total_views[0])
            - 1e-6
        )


def test_diagnosis_gives_a_score(glimpse, zoom):
    for env, params in (glimpse, zoom):
        _, state = env.reset(jax.random.key(0), params)
        n = env.num_actions
        for action, score in ((n - 1, 1.0), (n - 2, 0.0)):
            *_, terminated, truncated, info = env.step(jax.random.key(1), state, action, params)
            assert bool(terminated) and bool(info["declared"]) and float(info["score"]) == score
        *_, info = env.step(jax.random.key(1), state, 0, params)
        assert not bool(info["declared"]) and 0.0 <= float(info["score"]) <= 1.0


def _children(env, params, x, y):
    _, state = env.reset(jax.random.key(0), params)
    state = state.replace(x=jnp.int32(x), y=jnp.int32(y))
    state = state.replace(memory=env.action.init_memory(env, state, params))
    out = [env.step(jax.random.key(i), state, i, params)[1] for i in range(env.action.k**2)]
    assert all(int(c.z) == 1 for c in out)
    return state, out


def test_zoom_select_children(zoom, bundle):
    env, params = zoom
    # level 0 is 64 × 48 px, level 1 256 × 192 (zoom factor 4). The view at (16, 8) has its centre at
    # (32, 24), (128, 96) px of level 1; its footprint there is the 128-px square from (64, 32); k = 2
    # splits it into 64-px squares whose centres, less half a view, are the children's corners
    parent, children = _children(env, params, 16, 8)
    assert [(int(c.x), int(c.y)) for c in children] == [(80, 48), (144, 48), (80, 112), (144, 112)]
    _, back, *_ = env.step(jax.random.key(9), children[3], 4, params)  # action k² zooms out to the parent
    assert (int(back.z), int(back.x), int(back.y)) == (0, 16, 8)
    _, same, *_ = env.step(jax.random.key(9), back, 4, params)  # the coarsest level has no parent
    assert (int(same.z), int(same.x), int(same.y)) == (0, 16, 8)
    # with k equal to the zoom factor the children tile the footprint exactly
    env4, params4 = histojax.make(
        "HistoJAX-Easy-v0", slide=bundle, action_mode=ZoomSelect(k=4), task="classification", auto_reset=False
    )
    _, children = _children(env4, params4, 16, 8)
    assert sorted((int(c.x), int(c.y)) for c in children) == sorted(
        (64 + 32 * i, 32 + 32 * j) for i in range(4) for j in range(4)
    )


def test_zoom_select_counts_finest_views_read(zoom, zoom_rollout):
    env, params = zoom
    # in, in, then each of the four finest children of that view (out, in), then stay at the last
    actions = jnp.asarray([0, 0, 4, 1, 4, 2, 4, 3, 3, 3, 3], jnp.int32)
    states, infos, obs = zoom_rollout(jax.random.key(2), actions, params)
    total = int(params.mode_data.total_views[0])
    reads = np.round(np.asarray(infos["fraction_read"]) * total)
    assert reads[-1] <= 4 and np.all(np.diff(reads) >= 0)
    assert np.asarray(infos["fields_of_view"])[-1] == 6  # the start, one view at level 1, four at level 2
    assert np.asarray(states.z).tolist() == [1, 2, 1, 2, 1, 2, 1, 2, 2, 2, 2]
    assert np.all(np.asarray(obs["visited"]) >= 0) and np.all(np.asarray(obs["visited"]) <= 1)


def test_auc_matches_a_hand_computation():
    from data_tools.metrics import roc_auc

    # positives 0.35 and 0.8 against negatives 0.1 and 0.4: 0.35 beats 0.1 only, 0.8 beats both → 3 / 4
    assert roc_auc([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1]) == pytest.approx(0.75)
    # a tie counts one half: 0.5 vs 0.5 → (1 + 0.5) / 2
    assert roc_auc([0.5, 0.2, 0.5, 0.9], [0, 0, 1, 1]) == pytest.approx((2 + 1.5) / 4)
    assert np.isnan(roc_auc([0.1, 0.2], [1, 1]))  # one class only: undefined


def test_navigation_tracks_reading_without_changing_trajectories(bundle):
    plain, p0 = histojax.make("HistoJAX-Easy-v0", slide=bundle, auto_reset=False)
    tracked, p1 = histojax.make("HistoJAX-Easy-v0", slide=bundle, auto_reset=False, track_reading=True)
    actions = jax.random.randint(jax.random.key(4), (STEPS - 1,), 0, 7)
    s0, i0, o0 = jax.jit(_rollout(plain))(jax.random.key(8), actions, p0)
    s1, i1, o1 = jax.jit(_rollout(tracked))(jax.random.key(8), actions, p1)
    for f in ("z", "x", "y", "t"):
        np.testing.assert_array_equal(np.asarray(getattr(s0, f)), np.asarray(getattr(s1, f)))
    np.testing.assert_array_equal(np.asarray(o0), np.asarray(o1))
    assert s0.memory is None and "fraction_read" not in i0
    fraction = np.asarray(i1["fraction_read"])
    assert np.all(np.diff(fraction) >= 0) and np.all(fraction <= 1)
    # finest-level tissue views read = distinct finest views visited that hold tissue
    total = int(p1.mode_data.total_views[0])
    tissue = np.asarray(p1.mode_data.tissue[0])
    finest = np.asarray(s1.z) == 2
    views = {
        (int(y) + TILE // 2) // TILE * 32 + (int(x) + TILE // 2) // TILE
        for x, y in zip(np.asarray(s1.x)[finest], np.asarray(s1.y)[finest])
    }
    assert round(fraction[-1] * total) == sum(bool(tissue[v]) for v in views)


def test_navigation_memory_observation(bundle):
    from histojax.core.modes.base import Continuous, Discrete
    from histojax.core.modes.factory import action_mode

    env, params = histojax.make("HistoJAX-Easy-v0", slide=bundle, action_mode=Discrete(memory=True))
    obs, _ = env.reset(jax.random.key(0), params)
    assert set(obs) == {"pixels", "visited", "position"}
    assert env.observation_space(params).contains(obs)
    assert observation_bytes(env, params) == sum(np.asarray(v).nbytes for v in obs.values())
    # the same by name, as a trainer's JSON config spells it
    assert action_mode("discrete:memory") == Discrete(memory=True)
    assert action_mode("continuous:memory") == Continuous(memory=True)
    for bad in ("discrete:3", "glimpse:memory", "discrete:"):
        with pytest.raises(ValueError, match="action_mode"):
            action_mode(bad)


def test_offline_reader_reads_as_the_env(glimpse):
    from baselines.reading.orders import read_cells

    env, params = glimpse
    table = env.action.host_tables(env, params, env.bundles)[0]
    order = np.random.default_rng(0).permutation(np.flatnonzero(table["valid"]))
    for budget in (0.1, 0.3):
        cells, fraction = read_cells(table, order, budget)
        p = with_budget(params, budget)
        _, state = env.reset(jax.random.key(0), p)
        step = jax.jit(env.step)
        for c in order:
            _, state, _, _, truncated, info = step(jax.random.key(1), state, int(c), p)
            if bool(truncated):
                break
        assert float(info["fraction_read"]) == pytest.approx(fraction)
        assert sorted(np.flatnonzero(np.asarray(state.memory.revealed))) == sorted(cells.tolist())


# ----------------------------------------------------------------------------- step observation (step_obs=True, -v2)
def test_step_observation_holds_what_the_full_one_does(bundle):
    """``step_obs=True``: the same trajectory as the full (v1) observation, and the full observation is
    rebuilt from the step observation plus ``env.episode_tables``: cells and validity per slide, the
    summaries of the cells read (from the K slots), the read bits, the budget left."""
    from histojax.reading.modes.glimpse import unpack_bits

    kw = dict(
        slide=bundle,
        obs_mode="features",
        action_mode=Glimpse(level=1),
        task="classification",
        max_steps_in_episode=STEPS,
        auto_reset=False,
        read_budget=0.3,
    )
    full, pf = histojax.make("HistoJAX-Easy-v0", **kw)
    step, ps = histojax.make("HistoJAX-Easy-v0", step_obs=True, **kw)
    assert observation_bytes(step, ps) < observation_bytes(full, pf)
    actions = jax.random.randint(jax.random.key(3), (STEPS - 1,), 0, full.num_actions - 2)
    s0, i0, o0 = jax.jit(_rollout(full))(jax.random.key(9), actions, pf)
    s1, i1, o1 = jax.jit(_rollout(step))(jax.random.key(9), actions, ps)
    for k in ("fraction_read", "fields_of_view", "terminated", "truncated"):
        np.testing.assert_array_equal(np.asarray(i0[k]), np.asarray(i1[k]))
    np.testing.assert_array_equal(np.asarray(o0["budget_left"]), np.asarray(o1["budget_left"]))
    np.testing.assert_array_equal(np.asarray(o0["features"]), np.asarray(o1["features"]))
    tables = step.episode_tables(ps)
    c = int(ps.mode_data.valid.shape[-1])
    assert set(o1) == {"features", "slide", "read_bits", "read_cells", "read_summaries", "budget_left"}
    for t in range(STEPS - 1):
        i = int(o1["slide"][t])
        np.testing.assert_array_equal(np.asarray(tables["cells"][i]), np.asarray(o0["cells"][t]))
        np.testing.assert_array_equal(np.asarray(tables["valid"][i]), np.asarray(o0["valid"][t]))
        revealed = np.asarray(unpack_bits(o1["read_bits"][t], c)).astype(np.float32)
        np.testing.assert_array_equal(revealed, np.asarray(o0["revealed"][t]))
        rebuilt = np.zeros_like(np.asarray(o0["summaries"][t]))
        cells = np.asarray(o1["read_cells"][t])
        rebuilt[cells[cells < c]] = np.asarray(o1["read_summaries"][t])[cells < c]
        np.testing.assert_array_equal(rebuilt, np.asarray(o0["summaries"][t]))
        assert (cells < c).sum() == int(i1["fields_of_view"][t])


def test_read_slots_bound_the_cells_read(bundle):
    """``read_slots=K``: a (K+1)-th new cell reveals nothing and ends the episode, like the budget."""
    env, params = histojax.make(
        "HistoJAX-Easy-v0",
        slide=bundle,
        obs_mode="features",
        action_mode=Glimpse(level=1),
        task="classification",
        auto_reset=False,
        step_obs=True,
        read_slots=2,
    )
    valid = np.flatnonzero(np.asarray(params.mode_data.valid[0]))[:3]
    _, state = env.reset(jax.random.key(0), params)
    for j, c in enumerate(valid):
        obs, state, _, term, trunc, info = env.step(jax.random.key(1), state, int(c), params)
        assert bool(trunc) == (j == 2) and not bool(term)
    assert int(info["fields_of_view"]) == 2 and list(np.asarray(obs["read_cells"])) == list(valid[:2])
    with pytest.raises(ValueError, match="read_slots"):
        histojax.make(
            "HistoJAX-Easy-v0",
            slide=bundle,
            obs_mode="features",
            action_mode="glimpse:1",
            task="classification",
            step_obs=True,
            read_slots=0,
        )


def test_default_slots_hold_every_cell_the_budget_allows(bundle):
    from histojax.reading.modes.glimpse import slots_needed

    env, params = histojax.make(
        "HistoJAX-Easy-v0",
        slide=bundle,
        obs_mode="features",
        action_mode=Glimpse(level=1),
        task="classification",
        step_obs=True,
        read_budget=0.25,
    )
    t = params.mode_data
    k = int(t.slots_zero.shape[0])
    views = np.sort(np.asarray(t.cell_views[0])[np.asarray(t.valid[0])])
    budget = int(np.floor(np.float32(0.25) * int(t.total_views[0]) + 1e-4))
    assert views[:k].sum() <= budget and (k == len(views) or views[: k + 1].sum() > budget)
    assert slots_needed(np.asarray(t.cell_views), np.asarray(t.valid), np.asarray(t.total_views), 1.0) == len(views)


def test_mode_names_resolve_apart_from_the_base_classes():
    """``histojax.core.modes.base`` holds the base classes that ``glimpse`` and ``zoom_select`` import; the names
    resolve in ``histojax.core.modes.factory``, where the reading stack registers its modes, so the core imports
    neither reading mode (no circle)."""
    import ast
    import inspect

    from histojax.core.modes import base, factory

    imported = set()
    for node in ast.walk(ast.parse(inspect.getsource(base))):
        if isinstance(node, ast.ImportFrom):
            imported |= {node.module or ""} | {f"{node.module}.{a.name}" for a in node.names}
        elif isinstance(node, ast.Import):
            imported |= {a.name for a in node.names}
    assert not {m for m in imported if "glimpse" in m or "zoom_select" in m or "mode_registry" in m}
    assert isinstance(factory.action_mode("glimpse:2"), Glimpse)
    assert factory.action_mode("zoom_select:4") == ZoomSelect(k=4)
    assert not hasattr(base, "action_mode")
