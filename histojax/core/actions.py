"""Actions → new ``(z, x, y)``. Positions are top-left corners in px of level ``z``
(0 = coarsest); every result is clamped to ``[0, W_z - T] × [0, H_z - T]``."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from histojax.core.slide import SlideArrays

UP, DOWN, LEFT, RIGHT, ZOOM_IN, ZOOM_OUT, STAY = range(7)
DECLARE_NO_TUMOUR, DECLARE_TUMOUR = 7, 8  # task="classification" only
ACTION_NAMES = ("UP", "DOWN", "LEFT", "RIGHT", "ZOOM_IN", "ZOOM_OUT", "STAY", "DECLARE_NO_TUMOUR", "DECLARE_TUMOUR")
NUM_DISCRETE_ACTIONS = 7
ZOOM_THRESHOLD = 0.5  # continuous dzoom above +0.5 zooms in, below -0.5 zooms out


def clamp_position(slide: SlideArrays, z, x, y, tile_size: int):
    """Clamp a top-left corner so the ``T × T`` view lies inside level ``z``."""
    x = jnp.clip(x, 0, slide.level_width[z] - tile_size)
    y = jnp.clip(y, 0, slide.level_height[z] - tile_size)
    return x, y


def move_and_zoom(slide: SlideArrays, z, x, y, dx, dy, dz, tile_size: int, n_levels: int):
    """Translate by ``(dx, dy)`` px of level ``z``, clamp, then change level by ``dz`` in {-1, 0, 1}
    keeping the view's centre (in level-0 px) fixed, and clamp again. Returns int32 ``(z, x, y)``."""
    x, y = clamp_position(slide, z, x + dx, y + dy, tile_size)
    new_z = jnp.clip(z + dz, 0, n_levels - 1)
    ratio = slide.downsample[z] / slide.downsample[new_z]
    half = tile_size / 2.0
    new_x = jnp.round((x + half) * ratio - half).astype(jnp.int32)
    new_y = jnp.round((y + half) * ratio - half).astype(jnp.int32)
    new_x, new_y = clamp_position(slide, new_z, new_x, new_y, tile_size)
    return new_z.astype(jnp.int32), new_x, new_y


def discrete_deltas(action: jax.Array, stride_px: jax.Array):
    """HistoGym's codes → ``(dx, dy, dz)``: UP=0 (y−), DOWN=1 (y+), LEFT=2 (x−), RIGHT=3 (x+),
    ZOOM_IN=4 (z+1, finer), ZOOM_OUT=5 (z−1), STAY=6. Any other value is treated as STAY."""
    a = jnp.asarray(action, jnp.int32)
    dx = jnp.where(a == RIGHT, stride_px, 0) - jnp.where(a == LEFT, stride_px, 0)
    dy = jnp.where(a == DOWN, stride_px, 0) - jnp.where(a == UP, stride_px, 0)
    dz = (a == ZOOM_IN).astype(jnp.int32) - (a == ZOOM_OUT).astype(jnp.int32)
    return dx, dy, dz


def continuous_deltas(action: jax.Array, stride_px: jax.Array):
    """``action = (dx, dy, dzoom)`` float → ``(dx, dy, dz)``: ``dx, dy`` in view widths (× stride),
    clipped to ``[-1, 1]``, rounded to px; ``dzoom > 0.5`` zooms in, ``< -0.5`` zooms out.
    NaN counts as 0 and ±inf as ±1, so no input can put a NaN in the state."""
    a = jnp.clip(jnp.nan_to_num(jnp.asarray(action, jnp.float32), nan=0.0, posinf=1.0, neginf=-1.0), -1.0, 1.0)
    dx = jnp.round(a[0] * stride_px).astype(jnp.int32)
    dy = jnp.round(a[1] * stride_px).astype(jnp.int32)
    dz = (a[2] > ZOOM_THRESHOLD).astype(jnp.int32) - (a[2] < -ZOOM_THRESHOLD).astype(jnp.int32)
    return dx, dy, dz


def discrete_diagnosis(action: jax.Array) -> jax.Array:
    """Diagnosis declared by a discrete action: 1 (DECLARE_TUMOUR=8), 0 (DECLARE_NO_TUMOUR=7), or
    -1 (no diagnosis: any other action). int32."""
    a = jnp.asarray(action, jnp.int32)
    return jnp.where(a == DECLARE_TUMOUR, 1, jnp.where(a == DECLARE_NO_TUMOUR, 0, -1)).astype(jnp.int32)


def continuous_diagnosis(action: jax.Array) -> jax.Array:
    """Diagnosis in the 4th component of a continuous action: > 0.5 tumour (1), < -0.5 no tumour
    (0), else (or NaN) none (-1). int32."""
    d = jnp.nan_to_num(jnp.asarray(action, jnp.float32)[3], nan=0.0)
    return jnp.where(d > ZOOM_THRESHOLD, 1, jnp.where(d < -ZOOM_THRESHOLD, 0, -1)).astype(jnp.int32)
