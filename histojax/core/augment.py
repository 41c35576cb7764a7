"""Dihedral view augmentation: each episode is seen in one of the 8 orientations of the square
(4 rotations by 90°, each with or without a mirror), drawn at reset (``make(..., augment=True)``).

The environment keeps its state, rewards and termination in the slide's own frame; only what the
agent sees and how its actions are read change. Orientation ``o`` (int32 in ``0..7``) has an
integer matrix ``M_o`` acting on image coordinates ``(x → right, y → down)`` about the view's
centre; ``M_0`` is the identity:

* pixels: the observed view is the slide's view with every pixel moved by ``M_o``
  (:func:`orient_pixels`; one gather with a precomputed permutation of the ``T × T`` pixels);
* actions: a move the agent makes in its frame, ``d``, is the move ``M_o⁻¹ d`` on the slide
  (:func:`discrete_to_slide`, :func:`continuous_to_slide`); zoom, stay and diagnosis actions are
  unchanged;
* position: the normalised centre ``p`` is seen at ``M_o (p − ½) + ½`` (:func:`orient_position`).

So the agent sees a consistent rotated/mirrored slide: after moving RIGHT in its frame, what was on
the right of its view is now in the middle. An agent trained with ``augment=True`` sees 8 different
layouts of every training slide, which keeps it from memorising where the tumour lies.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from histojax.core import actions

NUM_ORIENTATIONS = 8
_ROT = np.array([[0, -1], [1, 0]], np.int32)  # 90° turn in image coords (x right, y down)
_MIRROR = np.array([[-1, 0], [0, 1]], np.int32)  # left ↔ right


def matrices() -> np.ndarray:
    """``(8, 2, 2)`` int32: ``M_o = ROT^(o % 4) @ MIRROR^(o // 4)``, acting on ``(x, y)`` columns."""
    out = []
    for o in range(NUM_ORIENTATIONS):
        m = np.linalg.matrix_power(_ROT, o % 4) @ np.linalg.matrix_power(_MIRROR, o // 4)
        out.append(m.astype(np.int32))
    return np.stack(out)


_MATRICES = matrices()
_INVERSES = np.round(np.linalg.inv(_MATRICES)).astype(np.int32)  # M_o⁻¹: the agent's frame → the slide's


@functools.lru_cache(maxsize=None)
def pixel_permutations(tile_size: int) -> np.ndarray:
    """``(8, T*T)`` int32: ``observed.flat[i] = view.flat[perm[o, i]]`` for a ``(T, T)`` view in
    row-major order (row = y, column = x)."""
    t = tile_size
    c = (t - 1) / 2.0
    ys, xs = np.mgrid[0:t, 0:t]
    out = np.empty((NUM_ORIENTATIONS, t * t), np.int32)
    for o, inv in enumerate(_INVERSES):
        # the observed pixel at (x, y) comes from the view pixel M⁻¹ ((x, y) − c) + c
        sx = inv[0, 0] * (xs - c) + inv[0, 1] * (ys - c) + c
        sy = inv[1, 0] * (xs - c) + inv[1, 1] * (ys - c) + c
        out[o] = (np.round(sy).astype(np.int64) * t + np.round(sx).astype(np.int64)).reshape(-1)
    return out


def orient_pixels(pixels: jax.Array, orientation: jax.Array) -> jax.Array:
    """The ``(T, T, C)`` view as seen in ``orientation`` (same shape and dtype)."""
    t, _, ch = pixels.shape
    perm = jnp.asarray(pixel_permutations(t))[orientation]
    return pixels.reshape(t * t, ch)[perm].reshape(t, t, ch)


def _move_table() -> np.ndarray:
    """``(8, 4)`` int32: the slide-frame code of the agent's UP, DOWN, LEFT, RIGHT."""
    unit = {actions.UP: (0, -1), actions.DOWN: (0, 1), actions.LEFT: (-1, 0), actions.RIGHT: (1, 0)}
    code = {v: k for k, v in unit.items()}
    table = np.zeros((NUM_ORIENTATIONS, 4), np.int32)
    for o, inv in enumerate(_INVERSES):
        for a in range(4):
            table[o, a] = code[tuple(int(v) for v in inv @ np.array(unit[a]))]
    return table


_MOVES = _move_table()


def discrete_to_slide(action: jax.Array, orientation: jax.Array) -> jax.Array:
    """The slide-frame code of a discrete action taken in ``orientation``: moves (0–3) are turned,
    every other code (zoom, stay, diagnosis, out of range) is returned unchanged. int32."""
    a = jnp.asarray(action, jnp.int32)
    is_move = (a >= 0) & (a < 4)
    return jnp.where(is_move, jnp.asarray(_MOVES)[orientation, jnp.clip(a, 0, 3)], a)


def continuous_to_slide(action: jax.Array, orientation: jax.Array) -> jax.Array:
    """A continuous action ``(dx, dy, dzoom[, diagnosis])`` taken in ``orientation`` with its move
    ``(dx, dy)`` turned into the slide's frame (``M_o⁻¹ (dx, dy)``), after NaN → 0 and clipping to
    ``[-1, 1]`` as :func:`histojax.core.actions.continuous_deltas` does. float32."""
    a = jnp.clip(jnp.nan_to_num(jnp.asarray(action, jnp.float32), nan=0.0, posinf=1.0, neginf=-1.0), -1.0, 1.0)
    inv = jnp.asarray(_INVERSES.astype(np.float32))[orientation]
    return a.at[:2].set(inv @ a[:2])


def orient_position(position: jax.Array, orientation: jax.Array) -> jax.Array:
    """``(x_centre, y_centre, z)`` normalised to ``[0, 1]`` as seen in ``orientation``: the centre
    turned about ``(½, ½)``, ``z`` unchanged. float32 ``(3,)``."""
    m = jnp.asarray(_MATRICES.astype(np.float32))[orientation]
    xy = m @ (position[:2] - 0.5) + 0.5
    return jnp.concatenate([xy, position[2:]]).astype(jnp.float32)
