"""The coarse map of ``discrete:map`` from a slide head's per-view scores (``make(..., map_head=FOLDER)``) instead
of one feature entry: a logit head's map equals ``map_feature`` of the entry it reads; a learned head's map is
its per-view scores of the coarse level's feature vectors; bad combinations are one line."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from slide_helpers import synth_feature_dataset

import histojax
from histojax.reading.coarse_map import coarse_maps
from histojax.reading.heads.learned import LearnedHead, init_params
from histojax.reading.heads.logit import LogitHead


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return synth_feature_dataset(tmp_path_factory.mktemp("coarse-map-head"), n_slides=2, negatives=1)


def _make(dataset, **kw):
    return histojax.make(
        "HistoJAX-Easy-v0", dataset=str(dataset), split="train", obs_mode="features", action_mode="discrete:map", **kw
    )


def test_a_logit_heads_map_is_its_entrys_map(dataset, tmp_path):
    folder = LogitHead(
        cal_a=jnp.float32(1.0), cal_b=jnp.float32(0.0), prior_logit=jnp.float32(0.0), dim=2, k=1, top=1, encoder=None
    ).save(tmp_path / "logit-head")
    _, by_entry = _make(dataset, map_feature=2)
    _, by_head = _make(dataset, map_head=str(folder))
    np.testing.assert_array_equal(np.asarray(by_head.mode_data.coarse_map), np.asarray(by_entry.mode_data.coarse_map))


def test_a_learned_heads_map_is_its_per_view_scores(dataset, tmp_path):
    env, params = _make(dataset, map_feature=0)
    d = int(params.slide.features.shape[-1])
    head = LearnedHead(params=init_params(jax.random.key(0), d, 8, 4), features_dim=d, hidden=8, attention=4)
    maps = coarse_maps(env, params, env.bundles, None, head=head)
    assert maps.shape[1:] == (16, 16) and np.isfinite(maps).all()
    # the same map as the entry map of a slide whose features were replaced by the head's per-view scores
    scores = np.asarray(head.view_logits(np.asarray(params.slide.features, np.float32)))
    swapped = params.replace(slide=params.slide.replace(features=jnp.asarray(scores)[..., None]))
    np.testing.assert_allclose(maps, coarse_maps(env, swapped, env.bundles, 0), rtol=1e-6, atol=1e-6)
    folder = head.save(tmp_path / "learned-head")
    _, from_folder = _make(dataset, map_head=str(folder))
    np.testing.assert_allclose(np.asarray(from_folder.mode_data.coarse_map), maps, rtol=1e-6, atol=1e-6)


def test_bad_combinations_are_one_line(dataset, tmp_path):
    with pytest.raises(TypeError, match="not both"):
        _make(dataset, map_feature=0, map_head="x")
    with pytest.raises(TypeError, match="map_head=HEAD"):
        histojax.make("HistoJAX-Easy-v0", dataset=str(dataset), split="train", obs_mode="features", map_head="x")
    env, params = _make(dataset, map_feature=0)
    d = int(params.slide.features.shape[-1])
    head = LearnedHead(params=init_params(jax.random.key(0), d + 1, 8, 4), features_dim=d + 1, hidden=8, attention=4)
    with pytest.raises(ValueError, match=f"a head of {d + 1}-d features") as e:
        coarse_maps(env, params, env.bundles, None, head=head)
    assert len(str(e.value).splitlines()) == 1
