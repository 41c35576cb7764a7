"""Start positions drawn from cumulative weights computed once (``SlideArrays.start_cdf``, set by ``make``)
are the very draws of the per-reset computation from the logits, so trajectories are unchanged."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from histojax.core.env import sample_index, sample_row
from histojax.core.slide import start_cdf


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_precomputed_cdf_gives_the_same_draw_as_the_logits():
    rng = np.random.default_rng(0)
    draw = jax.jit(lambda k, lg, c, s: (sample_index(k, lg), sample_row(k, c, s), sample_row(k, c[s])))
    for trial in range(60):
        h, w = (int(v) for v in rng.integers(1, 40, 2))
        logits = np.where(rng.random((3, h, w)) < rng.random(), 0.0, -np.inf).astype(np.float32)
        for s in range(3):
            if not np.isfinite(logits[s]).any():
                logits[s].flat[rng.integers(h * w)] = 0.0
        cdf = jnp.asarray(start_cdf(logits))
        for s in range(3):
            a, b, c = draw(jax.random.PRNGKey(trial * 3 + s), jnp.asarray(logits[s]).reshape(-1), cdf, s)
            assert int(a) == int(b) == int(c)
            assert np.isfinite(logits[s].reshape(-1)[int(a)])  # only allowed start positions


def test_make_sets_the_cdf_and_reset_is_unchanged_without_it():
    import histojax

    env, params = histojax.make("HistoJAX-Medium-v0")
    assert params.slide.start_cdf is not None
    bare = params.replace(slide=params.slide.replace(start_cdf=None))
    keys = jax.random.split(jax.random.PRNGKey(7), 32)
    reset = jax.jit(jax.vmap(env.reset, in_axes=(0, None)))
    (_, s1), (_, s2) = reset(keys, params), reset(keys, bare)
    for f in ("x", "y", "z", "slide_index"):
        np.testing.assert_array_equal(getattr(s1, f), getattr(s2, f))
