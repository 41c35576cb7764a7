"""Action and observation spaces: gymnax's own classes whenever gymnax can be imported.

With gymnax installed (``pip install histojax[gymnax]``), ``Discrete`` and ``Box`` *are*
``gymnax.environments.spaces.Discrete`` / ``Box`` and ``Dict`` is a subclass of gymnax's ``Dict``
(its ``contains`` also takes a plain ``dict`` observation, which gymnax's reads by attribute), so
``isinstance(space, gymnax.environments.spaces.Discrete)``, gymnax's wrappers and
``gymnax_space_to_gym_space`` all work. Without gymnax the stand-ins below take the same
constructor arguments and offer the same ``n``, ``low``, ``high``, ``shape``, ``dtype``,
``sample(key)`` and ``contains(x)``; nobody can then ask whether they are gymnax's.
"""
from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp

try:
    from gymnax.environments import spaces as _gymnax_spaces
except ImportError:  # gymnax is optional: the stand-ins below
    _gymnax_spaces = None

GYMNAX = _gymnax_spaces is not None


def _dict_contains(spaces: dict, x: Any) -> jax.Array:
    """True when ``x`` is a mapping with the same keys as ``spaces`` and each member is contained."""
    if not isinstance(x, Mapping) or set(x) != set(spaces):
        return jnp.asarray(False)
    return jnp.all(jnp.stack([jnp.asarray(spaces[k].contains(v)) for k, v in x.items()]))


if GYMNAX:
    Space = _gymnax_spaces.Space
    Discrete = _gymnax_spaces.Discrete
    Box = _gymnax_spaces.Box

    class Dict(_gymnax_spaces.Dict):
        """gymnax's ``Dict`` whose ``contains`` takes the ``dict`` observations histojax returns."""

        def contains(self, x: Any) -> jax.Array:
            """True when ``x`` has the same keys and each member is contained."""
            return _dict_contains(self.spaces, x)

        def __getitem__(self, name: str):
            return self.spaces[name]

else:
    class Space:
        """Base of the stand-in spaces."""

        def sample(self, key: jax.Array) -> jax.Array:
            raise NotImplementedError

        def contains(self, x: Any) -> jax.Array:
            raise NotImplementedError

    class Discrete(Space):
        """Integers ``0 … n-1`` (shape ``()``)."""

        def __init__(self, num_categories: int, *, dtype=jnp.int32):
            self.n = int(num_categories)
            self.shape: tuple[int, ...] = ()
            self.dtype = jnp.dtype(dtype)

        def sample(self, key: jax.Array) -> jax.Array:
            """A uniform random action."""
            return jax.random.randint(key, self.shape, 0, self.n, dtype=self.dtype)

        def contains(self, x: Any) -> jax.Array:
            """True when ``x`` is an integer in ``[0, n)``."""
            x = jnp.asarray(x)
            return jnp.logical_and(x >= 0, x < self.n) & (x == jnp.round(x))

        def __repr__(self) -> str:
            return f"Discrete({self.n}, dtype={self.dtype.name})"

    class Box(Space):
        """A real (or integer) array of ``shape`` with elementwise bounds ``low``, ``high``."""

        def __init__(self, low, high, shape: tuple[int, ...], dtype=jnp.float32):
            self.low = low
            self.high = high
            self.shape = tuple(shape)
            self.dtype = dtype

        def sample(self, key: jax.Array) -> jax.Array:
            """A uniform random element (integers: uniform over ``[low, high]``)."""
            if jnp.issubdtype(self.dtype, jnp.integer):
                return jax.random.randint(key, self.shape, self.low, jnp.asarray(self.high) + 1).astype(self.dtype)
            return jax.random.uniform(key, self.shape, minval=self.low, maxval=self.high).astype(self.dtype)

        def contains(self, x: Any) -> jax.Array:
            """True when ``x`` lies within the bounds (NaN is not contained)."""
            x = jnp.asarray(x)
            return jnp.all(x >= self.low) & jnp.all(x <= self.high)

        def __repr__(self) -> str:
            return f"Box(low={self.low}, high={self.high}, shape={self.shape}, dtype={jnp.dtype(self.dtype).name})"

    class Dict(Space):
        """A dictionary of named spaces."""

        def __init__(self, spaces: dict):
            self.spaces = dict(spaces)
            self.num_spaces = len(self.spaces)

        def sample(self, key: jax.Array) -> dict:
            """One sample per member space, with independent keys."""
            keys = jax.random.split(key, len(self.spaces))
            return {name: space.sample(k) for (name, space), k in zip(self.spaces.items(), keys)}

        def contains(self, x: Any) -> jax.Array:
            """True when ``x`` has the same keys and each member is contained."""
            return _dict_contains(self.spaces, x)

        def __getitem__(self, name: str):
            return self.spaces[name]

        def __repr__(self) -> str:
            return f"Dict({self.spaces})"
