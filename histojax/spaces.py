"""Action and observation spaces with gymnax's names: ``n``, ``shape``, ``dtype``, ``sample``, ``contains``."""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp


class Discrete:
    """Integers ``0 … n-1`` (shape ``()``)."""

    def __init__(self, num_categories: int, dtype=jnp.int32):
        self.n = int(num_categories)
        self.shape: tuple[int, ...] = ()
        self.dtype = dtype

    def sample(self, key: jax.Array) -> jax.Array:
        """A uniform random action."""
        return jax.random.randint(key, self.shape, 0, self.n).astype(self.dtype)

    def contains(self, x: Any) -> jax.Array:
        """True when ``x`` is an integer in ``[0, n)``."""
        x = jnp.asarray(x)
        return jnp.logical_and(x >= 0, x < self.n) & (x == jnp.round(x))

    def __repr__(self) -> str:
        return f"Discrete({self.n})"


class Box:
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
        """True when ``x`` has ``shape`` and lies within the bounds (NaN is not contained)."""
        x = jnp.asarray(x)
        if x.shape != self.shape:
            return jnp.asarray(False)
        return jnp.all(x >= self.low) & jnp.all(x <= self.high)

    def __repr__(self) -> str:
        return f"Box(low={self.low}, high={self.high}, shape={self.shape}, dtype={jnp.dtype(self.dtype).name})"


class Dict:
    """A dictionary of named spaces."""

    def __init__(self, spaces: dict):
        self.spaces = dict(spaces)

    def sample(self, key: jax.Array) -> dict:
        """One sample per member space, with independent keys."""
        keys = jax.random.split(key, len(self.spaces))
        return {name: space.sample(k) for (name, space), k in zip(self.spaces.items(), keys)}

    def contains(self, x: Any) -> jax.Array:
        """True when ``x`` has the same keys and each member is contained."""
        if not isinstance(x, dict) or set(x) != set(self.spaces):
            return jnp.asarray(False)
        return jnp.all(jnp.stack([jnp.asarray(self.spaces[k].contains(v)) for k, v in x.items()]))

    def __getitem__(self, name: str):
        return self.spaces[name]

    def __repr__(self) -> str:
        return f"Dict({self.spaces})"
