"""``stack_slides(..., consume=True)`` (what ``make`` uses for a dataset): the same stacked arrays, bit for bit,
and the slides' own arrays deleted once stacked, so a dataset is not held twice in host memory."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import histojax
from histojax.loading import stack_slides


@pytest.fixture(scope="module")
def slide():
    _, params = histojax.make("HistoJAX-Easy-v0")
    return params.slide


def _copy(slide):
    return jax.tree.map(lambda a: jnp.array(a, copy=True), slide)


def test_consume_stacks_the_same_and_deletes_the_slides(slide):
    kept = stack_slides([_copy(slide), _copy(slide)], weights=[1.0, 3.0])
    slides = [_copy(slide), _copy(slide)]
    consumed = stack_slides(slides, weights=[1.0, 3.0], consume=True)
    for a, b in zip(jax.tree.leaves(kept), jax.tree.leaves(consumed), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert all(leaf.is_deleted() for s in slides for leaf in jax.tree.leaves(s))


def test_consume_of_one_slide_keeps_what_it_returns(slide):
    one = _copy(slide)
    out = stack_slides([one], weights=[1.0], consume=True)
    assert not any(leaf.is_deleted() for leaf in jax.tree.leaves(out))
    for a, b in zip(jax.tree.leaves(out), jax.tree.leaves(stack_slides([_copy(slide)], weights=[1.0])), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
