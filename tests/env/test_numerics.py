"""Summed-area tables do not overflow: uint32 modulo-2**32 arithmetic, proven at 200,000 × 200,000 px.

A dense 200k × 200k mask (4·10¹⁰ px) cannot be held in memory, so the test builds the exact
summed-area values a fully-tumour (and a striped) mask of that size has at the corners of
views anywhere in it — ``S[i, j] = i · j`` (or the stripe count) in Python integers, far beyond
2**32 — reduces them modulo 2**32 as the device table stores them, and checks that the lookup
returns the exact fraction.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from histojax.core.slide import summed_area_table
from histojax.core.views import box_fraction

SIDE = 200_000
T = 128


def stored(value: int) -> jnp.ndarray:
    return jnp.uint32(value % 2**32)


def full_sat(i: int, j: int) -> int:
    return i * j  # every pixel is tumour


def striped_sat(i: int, j: int) -> int:
    return i * (j // 2 + j % 2)  # tumour in every even column


@settings(deadline=None, max_examples=200, derandomize=True)
@given(x=st.integers(0, SIDE - T), y=st.integers(0, SIDE - T))
def test_view_fraction_exact_at_200k_by_200k(x, y):
    for sat, expected in ((full_sat, 1.0), (striped_sat, 0.5)):
        corners = [sat(y, x), sat(y, x + T), sat(y + T, x), sat(y + T, x + T)]
        got = box_fraction(*(stored(c) for c in corners), T * T)
        assert float(got) == expected


def test_corner_values_really_overflow_int32():
    assert full_sat(SIDE, SIDE) > 2**35 and int(stored(full_sat(SIDE, SIDE))) < 2**32
    # a view at the far corner: every corner value is past 2**32, the lookup is still exact
    x = y = SIDE - T
    corners = [full_sat(y, x), full_sat(y, x + T), full_sat(y + T, x), full_sat(y + T, x + T)]
    assert min(corners) > 2**32
    assert float(box_fraction(*(stored(c) for c in corners), T * T)) == 1.0


def test_host_table_matches_cumsum_and_wraps_consistently():
    rng = np.random.default_rng(0)
    mask = rng.integers(0, 2, (300, 400)).astype(np.uint8)
    sat = summed_area_table(mask)
    assert sat[-1, -1] == mask.sum() and sat.dtype == np.int64
    wrapped = (sat + 2**32 - 5).astype(np.uint64).astype(np.uint32)  # an offset that overflows every entry
    y, x = 17, 33
    got = box_fraction(*(jnp.uint32(wrapped[r, c]) for r, c in ((y, x), (y, x + T), (y + T, x), (y + T, x + T))), T * T)
    assert float(got) == mask[y : y + T, x : x + T].sum() / T**2
