"""Action and observation spaces: gymnax's own classes whenever gymnax can be imported.

With gymnax installed (``pip install histojax[gymnax]``), ``Discrete`` and ``Box`` *are*
``gymnax.environments.spaces.Discrete`` / ``Box`` and ``Dict`` is a subclass of gymnax's ``Dict``
(its ``contains`` also takes a plain ``dict`` observation, which gymnax's reads by attribute), so
``isinstance(space, gymnax.environments.spaces.Discrete)``, gymnax's wrappers and
``gymnax_space_to_gym_space`` all work. Without gymnax the stand-ins below take the same
constructor arguments and offer the same ``n``, ``low``, ``high``, ``shape``, ``dtype``,
``sample(key)`` and ``contains(x)``; nobody can then ask whether they are gymnax's.

The env declares its spaces once (``env.observation_space(params)``, ``env.action_space(params)``);
every bridge converts them here, never re-derives them: :func:`to_gymnasium` (Gymnasium and
Stable-Baselines3) and :func:`to_numpy` (HistoGym's API: gym-style spaces of numpy values with their
own seedable generator).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from histojax.core import gymnax_classes

try:  # gymnax's spaces module alone, not all of gymnax (see histojax.core.gymnax_classes)
    _gymnax_spaces = gymnax_classes.load("spaces")
except ImportError:  # gymnax is optional: the stand-ins below
    _gymnax_spaces = None

GYMNAX = _gymnax_spaces is not None


def _dict_contains(spaces: dict, x: Any) -> jax.Array:
    """True when ``x`` is a mapping with the same keys as ``spaces`` and each member is contained, or an
    object (e.g. an ``EnvState``) with an attribute for every key, each contained (gymnax's reading)."""
    if isinstance(x, Mapping):
        if set(x) != set(spaces):
            return jnp.asarray(False)
        members = x
    elif all(hasattr(x, k) for k in spaces):
        members = {k: getattr(x, k) for k in spaces}
    else:
        return jnp.asarray(False)
    return jnp.all(jnp.stack([jnp.asarray(spaces[k].contains(v)) for k, v in members.items()]))


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


# ----------------------------------------------------------------------------- converters for the bridges
def _bound(value):
    """A space bound as numpy (a Python scalar stays a scalar)."""
    return value if isinstance(value, (int, float)) else np.asarray(value)


def to_gymnasium(space):
    """The ``gymnasium.spaces`` equivalent of a histojax (gymnax) ``Discrete`` / ``Box`` / ``Dict``
    (needs gymnasium)."""
    from gymnasium import spaces as gym_spaces

    if isinstance(space, Discrete):
        return gym_spaces.Discrete(int(space.n))
    if isinstance(space, Box):
        return gym_spaces.Box(_bound(space.low), _bound(space.high), tuple(space.shape), np.dtype(space.dtype))
    if isinstance(space, Dict):
        return gym_spaces.Dict({name: to_gymnasium(s) for name, s in space.spaces.items()})
    raise TypeError(f"no Gymnasium space for {space!r}")


def channel_first(space):
    """An image ``Box`` ``(H, W, C)`` as ``(C, H, W)`` (HistoGym's observation layout)."""
    h, w, c = space.shape
    return Box(space.low, space.high, (c, h, w), space.dtype)


class NumpyDiscrete:
    """A gym-style ``Discrete(n)``: ``.n``, ``.sample()`` (a numpy int64), ``.contains(x)``, ``.seed(s)``."""

    def __init__(self, n: int, seed: int | None = None):
        self.n = int(n)
        self.shape: tuple[int, ...] = ()
        self.dtype = np.int64
        self._rng = np.random.default_rng(seed)

    def seed(self, seed: int | None = None) -> list[int | None]:
        self._rng = np.random.default_rng(seed)
        return [seed]

    def sample(self) -> np.int64:
        return np.int64(self._rng.integers(self.n))

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return bool(x.shape == () and np.issubdtype(x.dtype, np.integer) and 0 <= int(x) < self.n)

    def __repr__(self) -> str:
        return f"Discrete({self.n})"


class NumpyBox:
    """A gym-style ``Box`` of numpy arrays: ``low``, ``high``, ``shape``, ``dtype``, ``sample()``, ``contains(x)``."""

    def __init__(self, low, high, shape: tuple[int, ...], dtype=np.uint8, seed: int | None = None):
        self.low, self.high, self.shape, self.dtype = low, high, tuple(shape), np.dtype(dtype)
        self._rng = np.random.default_rng(seed)

    def seed(self, seed: int | None = None) -> list[int | None]:
        self._rng = np.random.default_rng(seed)
        return [seed]

    def sample(self) -> np.ndarray:
        if np.issubdtype(self.dtype, np.integer):
            return self._rng.integers(self.low, int(self.high) + 1, self.shape).astype(self.dtype)
        return self._rng.uniform(self.low, self.high, self.shape).astype(self.dtype)

    def contains(self, x) -> bool:
        x = np.asarray(x)
        return bool(x.shape == self.shape and np.all(x >= self.low) and np.all(x <= self.high))

    def __repr__(self) -> str:
        return f"Box({self.low}, {self.high}, {self.shape}, {self.dtype.name})"


def to_numpy(space, seed: int | None = None):
    """The gym-style numpy equivalent (:class:`NumpyDiscrete` / :class:`NumpyBox`, sampled from a
    ``numpy`` generator seeded with ``seed``) of a histojax ``Discrete`` / ``Box``."""
    if isinstance(space, Discrete):
        return NumpyDiscrete(int(space.n), seed=seed)
    if isinstance(space, Box):
        return NumpyBox(_bound(space.low), _bound(space.high), tuple(space.shape), np.dtype(space.dtype), seed=seed)
    raise TypeError(f"no numpy space for {space!r}")
