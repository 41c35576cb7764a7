"""The view at ``(z, x, y)``: a ``T × T`` crop of level ``z`` whose top-left corner is at
``(x, y)`` px of that level. Pure JAX; one gather of ``T`` contiguous rows.

For a tiled slide (``slide.tile_pool`` set; the branch is static) a view that need not be
tile-aligned covers at most 2 × 2 tiles: each view row is two ``T``-px slices (from its left and its
right tile) and a select, and the tumour fraction sums at most four sub-boxes, each from its tile's
local summed-area table. Still O(1) per view."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from histojax.core.slide import SlideArrays


def view_pixels(slide: SlideArrays, z: jax.Array, x: jax.Array, y: jax.Array, tile_size: int) -> jax.Array:
    """RGB uint8 ``(tile_size, tile_size, 3)`` of level ``z`` at top-left ``(x, y)`` (px of level ``z``).

    The caller keeps ``(x, y)`` inside ``[0, W_z - T] × [0, H_z - T]``."""
    if not slide.has_pixels:
        raise ValueError(
            "this slide was loaded without pixels (the feature-only layout of obs_mode='features'); "
            "make the env with obs_mode='pixels' to see pixels"
        )
    if slide.tile_pool is not None:
        return _tiled_view_pixels(slide, z, x, y, tile_size)
    rows = slide.level_offset[z] + (y + jnp.arange(tile_size)) * slide.level_width[z] + x
    return jax.vmap(lambda start: lax.dynamic_slice(slide.pixels, (start, 0), (tile_size, 3)))(rows)


def view_tumour_fraction(slide: SlideArrays, z: jax.Array, x: jax.Array, y: jax.Array, tile_size: int) -> jax.Array:
    """Fraction in ``[0, 1]`` (float32) of the view's pixels that are tumour, from the summed-area
    table of level ``z``: four lookups, O(1) whatever the view size (uint32 arithmetic modulo
    2**32, exact for any level size; see :mod:`histojax.core.slide`)."""
    if slide.sat_pool is not None:  # tiled (with or without pixels)
        return _tiled_tumour_fraction(slide, z, x, y, tile_size)
    stride = slide.level_width[z] + 1
    base = slide.sat_offset[z]

    def at(row, col):
        return slide.tumour_sat[base + row * stride + col]

    return box_fraction(
        at(y, x), at(y, x + tile_size), at(y + tile_size, x), at(y + tile_size, x + tile_size), tile_size * tile_size
    )


def box_fraction(top_left, top_right, bottom_left, bottom_right, area: int) -> jax.Array:
    """``(S[br] - S[tr] - S[bl] + S[tl]) / area`` from uint32 summed-area values kept modulo 2**32.

    Wrapping subtraction gives the box sum modulo 2**32, which is the exact sum when the box
    holds fewer than 2**32 px, whatever the (overflowed) corner values are."""
    count = bottom_right - top_right - bottom_left + top_left  # uint32, wraps
    return count.astype(jnp.float32) / float(area)


def _tile_cells(slide: SlideArrays, z, x, y, tile_size: int):
    """Grid position of the view's top-left tile, the offsets inside it, and the grid size."""
    t = tile_size
    gw = slide.tile_grid_width[z]
    gh = (slide.level_height[z] + t - 1) // t
    tx0, ox = jnp.divmod(x, t)
    ty0, oy = jnp.divmod(y, t)
    return tx0, ty0, ox, oy, gw, gh


def _tiled_view_pixels(slide: SlideArrays, z, x, y, tile_size: int) -> jax.Array:
    """Each view row ``r`` lies in tile row ``rr`` of a left and a right tile: two ``T``-px slices of the
    flat pool (the left tile's row from column ``ox``, the right tile's row shifted by ``T - ox``) and a
    select. A slice may run past its tile row, into the next row (or the pool's trailing spare tile),
    or start before the pool (only for the right tile 0 in row 0 — clamped to 0, still inside tile 0,
    which is uniform): those px are never selected, or equal the selected ones."""
    t = tile_size
    tx0, ty0, ox, oy, gw, gh = _tile_cells(slide, z, x, y, t)
    r = oy + jnp.arange(t)  # view rows in the 2-tile-high block, 0 .. 2T-2
    ty = jnp.minimum(ty0 + r // t, gh - 1)
    rr = r % t
    cells = slide.tile_offset[z] + ty * gw
    left = slide.tile_index[cells + tx0]
    right = slide.tile_index[cells + jnp.minimum(tx0 + 1, gw - 1)]
    flat = slide.tile_pool.reshape(-1, 3)  # (N*T*T, 3)
    row = lambda start: lax.dynamic_slice(flat, (start, 0), (t, 3))  # noqa: E731
    from_left = jax.vmap(row)(left * (t * t) + rr * t + ox)
    from_right = jax.vmap(row)(right * (t * t) + rr * t + ox - t)
    return jnp.where((jnp.arange(t) < t - ox)[None, :, None], from_left, from_right)


def _tiled_tumour_fraction(slide: SlideArrays, z, x, y, tile_size: int) -> jax.Array:
    t, s = tile_size, tile_size + 1
    tx0, ty0, ox, oy, gw, gh = _tile_cells(slide, z, x, y, t)
    flat = slide.sat_pool.reshape(-1)
    count = jnp.zeros((), jnp.uint32)
    for a in (0, 1):
        r0, r1 = (oy, t) if a == 0 else (0, oy)
        ty = jnp.minimum(ty0 + a, gh - 1)
        for b in (0, 1):
            c0, c1 = (ox, t) if b == 0 else (0, ox)
            tx = jnp.minimum(tx0 + b, gw - 1)
            base = slide.sat_index[slide.tile_offset[z] + ty * gw + tx] * (s * s)
            corner = lambda row, col: flat[base + row * s + col]  # noqa: E731
            count = count + (corner(r1, c1) - corner(r0, c1) - corner(r1, c0) + corner(r0, c0))  # uint32
    return count.astype(jnp.float32) / float(t * t)
