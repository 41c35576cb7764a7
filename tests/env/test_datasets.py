"""Multi-slide datasets and the classification task."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import tifffile

import histojax
from data_tools.bundle import build_bundle
from histojax.core.actions import DECLARE_NO_TUMOUR, DECLARE_TUMOUR, STAY
from histojax.sample import SAMPLE_ANNOTATIONS, SAMPLE_SLIDE

KEY = jax.random.PRNGKey(0)


@pytest.fixture(scope="module")
def two_slides(tmp_path_factory):
    """The sample slide (tumour annotated) and a smaller blank slide (no annotation), Easy levels."""
    root = tmp_path_factory.mktemp("dataset")
    a = build_bundle(
        SAMPLE_SLIDE, root / "sample", annotations_path=SAMPLE_ANNOTATIONS, level_sets=(3,), progress=False
    )
    rng = np.random.default_rng(1)
    tifffile.imwrite(root / "blank.tif", rng.integers(200, 255, (700, 900, 3), dtype=np.uint8), photometric="rgb")
    b = build_bundle(root / "blank.tif", root / "blank", level_sets=(3,), progress=False)
    (root / "dataset.json").write_text('{"train": ["sample"], "test": ["blank"]}')
    return root, a, b


def test_reset_draws_slides_by_weight_and_views_stay_inside_their_slide(two_slides):
    root, a, b = two_slides
    env, params = histojax.make("HistoJAX-Easy-v0", slides=[a, b], slide_weights=[1, 3])
    assert params.slide.num_slides == 2 and params.slide.level_width.shape == (2, 3)
    keys = jax.random.split(KEY, 2000)
    _, states = jax.vmap(env.reset, in_axes=(0, None))(keys, params)
    share = float(jnp.mean(states.slide_index == 1))
    assert 0.70 < share < 0.80  # weight 3 of 4
    # random rollouts of the first 400 (each step observes a 128-px view per env): every view stays inside the
    # level of its own slide
    n = 400
    step = jax.jit(jax.vmap(env.step, in_axes=(0, 0, 0, None)))
    s = jax.tree.map(lambda a: a[:n], states)
    assert 0 < int(jnp.sum(s.slide_index == 1)) < n  # both slides among them
    for i in range(30):
        k = jax.random.fold_in(KEY, i)
        actions = jax.random.randint(k, (n,), 0, 7)
        obs, s, reward, *_ = step(jax.random.split(k, n), s, actions, params)
        w = np.asarray(params.slide.level_width)[np.asarray(s.slide_index), np.asarray(s.z)]
        h = np.asarray(params.slide.level_height)[np.asarray(s.slide_index), np.asarray(s.z)]
        assert np.all(np.asarray(s.x) + 128 <= w) and np.all(np.asarray(s.y) + 128 <= h)
        assert bool(jnp.all(jnp.isfinite(reward)))


def test_observation_comes_from_the_state_slide(two_slides):
    root, a, b = two_slides
    env, params = histojax.make("HistoJAX-Easy-v0", slides=[a, b])
    for index, bundle in enumerate(env.bundles):
        s = histojax.EnvState(
            z=jnp.int32(2), x=jnp.int32(100), y=jnp.int32(200), t=jnp.int32(0), slide_index=jnp.int32(index)
        )
        np.testing.assert_array_equal(np.asarray(env.get_obs(s, params)), bundle.pixels[2][200:328, 100:228])
    picture = env.render(s, params)
    assert picture.ndim == 3


def test_dataset_folder_and_split(two_slides):
    root, a, b = two_slides
    env, params = histojax.make("HistoJAX-Easy-v0", dataset=root, split="test")
    assert params.slide.num_slides == 1 and env.bundles[0].path.name == "blank"
    with pytest.raises(ValueError, match="split"):
        histojax.make("HistoJAX-Easy-v0", dataset=root, split="validation")


def test_classification_rewards_a_right_diagnosis(two_slides):
    root, a, b = two_slides
    env, params = histojax.make("HistoJAX-Easy-v0", slides=[a, b], task="classification", auto_reset=False)
    assert env.action_space(params).n == 9
    assert [int(v) for v in params.slide.slide_label] == [1, 0]  # from the annotations
    low, high = env.reward_range(params)
    for index, label in ((0, 1), (1, 0)):
        s = histojax.EnvState(
            z=jnp.int32(0), x=jnp.int32(0), y=jnp.int32(0), t=jnp.int32(0), slide_index=jnp.int32(index)
        )
        right = DECLARE_TUMOUR if label else DECLARE_NO_TUMOUR
        wrong = DECLARE_NO_TUMOUR if label else DECLARE_TUMOUR
        _, _, r, term, trunc, info = env.step(KEY, s, right, params)
        assert bool(term) and bool(info["success"]) and float(r) == pytest.approx(high)
        _, _, r, term, _, info = env.step(KEY, s, wrong, params)
        assert bool(term) and not bool(info["success"]) and float(r) == pytest.approx(low)
        _, _, r, term, _, _ = env.step(KEY, s, STAY, params)
        assert not bool(term) and float(r) == pytest.approx(-params.step_cost)


def test_classification_labels_override_and_continuous(two_slides, tmp_path):
    root, a, b = two_slides
    csv = tmp_path / "labels.csv"
    csv.write_text("slide,label\nsample,0\nblank,1\n")
    env, params = histojax.make(
        "HistoJAX-Easy-v0", slides=[a, b], task="classification", labels=csv, action_mode="continuous", auto_reset=False
    )
    assert [int(v) for v in params.slide.slide_label] == [0, 1]
    assert env.action_space(params).shape == (4,)
    s = histojax.EnvState(z=jnp.int32(0), x=jnp.int32(0), y=jnp.int32(0), t=jnp.int32(0), slide_index=jnp.int32(1))
    _, _, r, term, _, info = env.step(KEY, s, jnp.array([0.0, 0.0, 0.0, 0.9]), params)  # declares tumour
    assert bool(term) and bool(info["success"])
    _, _, _, term, _, _ = env.step(KEY, s, jnp.array([0.0, 0.0, 0.0, jnp.nan]), params)
    assert not bool(term)
