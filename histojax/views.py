"""The view at ``(z, x, y)``: a ``T × T`` crop of level ``z`` whose top-left corner is at
``(x, y)`` px of that level. Pure JAX; one gather of ``T`` contiguous rows."""
from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from histojax.slide import SlideArrays


def view_pixels(slide: SlideArrays, z: jax.Array, x: jax.Array, y: jax.Array, tile_size: int) -> jax.Array:
    """RGB uint8 ``(tile_size, tile_size, 3)`` of level ``z`` at top-left ``(x, y)`` (px of level ``z``).

    The caller keeps ``(x, y)`` inside ``[0, W_z - T] × [0, H_z - T]``."""
    rows = slide.level_offset[z] + (y + jnp.arange(tile_size)) * slide.level_width[z] + x
    return jax.vmap(lambda start: lax.dynamic_slice(slide.pixels, (start, 0), (tile_size, 3)))(rows)


def view_tumour_fraction(slide: SlideArrays, z: jax.Array, x: jax.Array, y: jax.Array, tile_size: int) -> jax.Array:
    """Fraction in ``[0, 1]`` (float32) of the view's pixels that are tumour, from the summed-area
    table of level ``z``: four lookups, O(1) whatever the view size (uint32 arithmetic modulo
    2**32, exact for any level size; see :mod:`histojax.slide`)."""
    stride = slide.level_width[z] + 1
    base = slide.sat_offset[z]

    def at(row, col):
        return slide.tumour_sat[base + row * stride + col]

    return box_fraction(at(y, x), at(y, x + tile_size), at(y + tile_size, x), at(y + tile_size, x + tile_size),
                        tile_size * tile_size)


def box_fraction(top_left, top_right, bottom_left, bottom_right, area: int) -> jax.Array:
    """``(S[br] - S[tr] - S[bl] + S[tl]) / area`` from uint32 summed-area values kept modulo 2**32.

    Wrapping subtraction gives the box sum modulo 2**32, which is the exact sum when the box
    holds fewer than 2**32 px, whatever the (overflowed) corner values are."""
    count = bottom_right - top_right - bottom_left + top_left  # uint32, wraps
    return count.astype(jnp.float32) / float(area)
