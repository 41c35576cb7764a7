"""Action and observation modes: small objects that ``HistoEnv`` calls; it never compares a mode name.

An **action mode** turns an action into the next position (and, for ``task="classification"``, a
diagnosis with a score) and declares its action space; a mode that reads the slide in its own way
(``glimpse``, ``zoom_select``) also keeps a *memory* in ``EnvState.memory`` (``None`` for the
navigation modes, so their state is HistoGym's ``(z, x, y, t, …)`` as before), may put precomputed
per-slide tables in ``EnvParams.mode_data`` (``prepare``, called once by ``make``) and adds entries
to the observation (``memory_obs``). An **observation mode** turns a state into the view's
observation and declares its space.

This module holds the base classes, the pan/zoom navigation modes (``Discrete``, ``Continuous``) and the
observation modes (``Pixels``, ``Features``): the env core's own. The reading modes (``glimpse``,
``zoom_select``) subclass :class:`ActionMode` in :mod:`histojax.reading.modes`. Adding a mode is one new object (a
frozen, hashable dataclass, so the env stays a valid static argument of ``jax.jit``) plus its name in
:mod:`histojax.core.modes.factory` (:func:`~histojax.core.modes.factory.register_action_mode`), where the strings
users pass to ``make(..., action_mode="discrete")`` are resolved.
"""

from __future__ import annotations

import dataclasses
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from histojax.core import actions, seen_views, spaces
from histojax.core import augment as dihedral
from histojax.core.views import view_pixels


class Move(NamedTuple):
    """What an action mode's ``apply`` returns (all traced scalars unless said otherwise)."""

    z: jax.Array  # int32 level of the next view (0 = coarsest)
    x: jax.Array  # int32 top-left corner of the next view, px of level z
    y: jax.Array  # int32
    diagnosis: jax.Array  # int32: 1 tumour, 0 no tumour, -1 none declared (classification only)
    score: jax.Array  # float32 in [0, 1]: the declared belief that the slide holds tumour
    memory: Any = None  # the mode's new memory pytree (None for memory-less modes)


# ----------------------------------------------------------------------------- action modes
@dataclasses.dataclass(frozen=True)
class ActionMode:
    """Base of the action modes (see the module doc). Subclasses override what they need."""

    name = "base"
    supports_augment = False  # the 8-orientation augmentation can turn this mode's actions
    needs_features = False  # make() must load the bundles' feature grids
    tasks = ("detection", "classification")

    def validate(self, env) -> None:
        """Raise ``ValueError`` for settings this mode cannot serve (one clear line)."""
        if env.task not in self.tasks:
            raise ValueError(f"action_mode={self.name!r} supports task in {self.tasks}, got {env.task!r}")

    def num_actions(self, env) -> int:
        raise NotImplementedError

    def space(self, env, params):
        raise NotImplementedError

    def prepare(self, env, params, bundles, **settings):
        """Per-slide tables for ``params.mode_data`` (host side, once, in ``make``; ``settings`` such
        as ``read_budget`` come from ``make``'s keywords); ``None`` if none."""
        if settings:
            raise TypeError(f"action_mode={self.name!r} takes no {sorted(settings)}")
        return None

    def init_memory(self, env, state, params):
        """The memory of a fresh episode at ``state`` (``None``: this mode keeps none)."""
        return None

    def auto_reset_memory(self, env, done, memory, state, params):
        """The memory :meth:`histojax.core.env.HistoEnv.step` keeps after its auto-reset: a fresh episode's at
        ``state`` (the state kept, the new episode's where ``done``) where ``done`` (bool scalar), else
        ``memory``, the stepped one. By default a select over the whole memory; a mode whose memory is
        large overrides it to write only what a new episode changes."""
        fresh = self.init_memory(env, state, params)
        return jax.tree.map(lambda a, b: jnp.where(done, a, b), fresh, memory)

    def apply(self, env, state, action, params) -> Move:
        raise NotImplementedError

    def memory_obs(self, env, state, params) -> dict:
        """Extra observation entries built from the memory (``{}``: none)."""
        return {}

    def memory_space(self, env, params) -> dict:
        """Spaces of :meth:`memory_obs`'s entries."""
        return {}

    def episode_tables(self, env, params) -> dict:
        """Per-slide arrays fixed during an episode, for a policy to index with the observation's slide
        (:meth:`histojax.core.env.HistoEnv.episode_tables`); ``{}``: none."""
        return {}

    def budget_spent(self, env, state, params) -> jax.Array:
        """True when the episode's reading budget is spent (it is then truncated); never by default."""
        return jnp.zeros((), bool)

    def reading_info(self, env, state, params) -> dict:
        """Efficiency figures for ``info`` (``{}`` when this mode does not track reading)."""
        return {}


def _declared_score(diagnosis):
    """A hard diagnosis as a score: 1.0 tumour, 0.0 no tumour, 0.5 none."""
    return jnp.where(diagnosis < 0, 0.5, diagnosis.astype(jnp.float32)).astype(jnp.float32)


@dataclasses.dataclass(frozen=True)
class Navigation(ActionMode):
    """Base of the pan/zoom modes. They keep no memory unless asked: ``make(..., track_reading=True)``
    (``fraction_read`` / ``fields_of_view`` in ``info``; ``read_budget`` truncates) or
    ``memory=True`` (that, plus the coarse ``visited`` map and ``position`` in the observation; see
    :mod:`histojax.core.seen_views`). Without either the state and the trajectories are HistoGym's."""

    memory: bool = False
    coarse_map: bool = (
        False  # with memory: the observation also holds ``coarse_map (16, 16)`` (built by the reading stack)
    )
    supports_augment = True

    @property
    def needs_features(self) -> bool:
        return self.coarse_map  # the map is built from the slides' feature grids

    def prepare(
        self,
        env,
        params,
        bundles,
        track_reading: bool = False,
        read_budget: float | None = None,
        map_feature: int | None = None,
        map_level: int = -3,
        map_head=None,
    ):
        """``map_feature`` / ``map_head`` / ``map_level`` (``coarse_map=True`` only): the feature entry, or the slide
        head (a folder or a loaded head) whose per-view scores the coarse map shows, and the level of the coarse map
        (:func:`histojax.core.seen_views.coarse_maps`, the builder the reading stack registers)."""
        if map_feature is not None and map_head is not None:
            raise TypeError(f"{self.name}:map shows map_feature=ENTRY or map_head=HEAD, not both")
        if self.coarse_map and map_feature is None and map_head is None:
            raise TypeError(
                f"{self.name}:map needs map_feature=ENTRY (the feature entry its coarse map shows) or "
                "map_head=HEAD (a slide head's per-view scores)"
            )
        if not self.coarse_map and (map_feature is not None or map_head is not None):
            given = "map_feature" if map_feature is not None else "map_head=HEAD (a slide head's per-view map)"
            raise TypeError(f"{given} is for {self.name}:map only")
        if not (self.memory or track_reading):
            if read_budget is not None:
                raise TypeError(f"read_budget needs track_reading=True (or {self.name} with memory=True)")
            return None
        tables = seen_views.seen_tables(env, params, bundles, 1.0 if read_budget is None else read_budget)
        if self.coarse_map:
            tables = tables.replace(
                coarse_map=jnp.asarray(
                    seen_views.coarse_maps(env, params, bundles, map_feature, map_level, head=map_head)
                )
            )
        return tables

    def init_memory(self, env, state, params):
        return None if params.mode_data is None else seen_views.init_seen(params.mode_data, state, env)

    def _seen(self, env, state, params, z, x, y):
        if state.memory is None:
            return None
        return seen_views.see(params.mode_data, state.memory, state.slide_index, z, x, y, env)

    def budget_spent(self, env, state, params) -> jax.Array:
        if state.memory is None:
            return super().budget_spent(env, state, params)
        return seen_views.budget_spent(params.mode_data, state.memory, state.slide_index)

    def reading_info(self, env, state, params) -> dict:
        if state.memory is None:
            return {}
        return seen_views.reading_info(params.mode_data, state.memory, state.slide_index)

    def memory_obs(self, env, state, params) -> dict:
        if not self.memory:
            return {}
        obs = seen_views.visited_obs(env, state, params)
        if self.coarse_map:
            obs["coarse_map"] = params.mode_data.coarse_map[state.slide_index]
        return obs

    def memory_space(self, env, params) -> dict:
        if not self.memory:
            return {}
        space = seen_views.visited_space(params)
        if self.coarse_map:
            space["coarse_map"] = spaces.Box(
                -jnp.inf, jnp.inf, (seen_views.VISITED_MAP, seen_views.VISITED_MAP), jnp.float32
            )
        return space


@dataclasses.dataclass(frozen=True)
class Discrete(Navigation):
    """HistoGym's ``Discrete(7)`` moves (+ DECLARE_NO_TUMOUR=7, DECLARE_TUMOUR=8 for classification)."""

    name = "discrete"

    def num_actions(self, env) -> int:
        return actions.NUM_DISCRETE_ACTIONS + (2 if env.task == "classification" else 0)

    def space(self, env, params):
        return spaces.Discrete(self.num_actions(env))

    def apply(self, env, state, action, params) -> Move:
        slide = params.slide.select(state.slide_index)
        if env.augment:  # the agent acts in its turned frame
            action = dihedral.discrete_to_slide(action, state.orientation)
        stride_px = jnp.round(params.stride * env.tile_size).astype(jnp.int32)
        dx, dy, dz = actions.discrete_deltas(action, stride_px)
        z, x, y = actions.move_and_zoom(slide, state.z, state.x, state.y, dx, dy, dz, env.tile_size, env.n_levels)
        diagnosis = actions.discrete_diagnosis(action)
        return Move(z, x, y, diagnosis, _declared_score(diagnosis), self._seen(env, state, params, z, x, y))


@dataclasses.dataclass(frozen=True)
class Continuous(Navigation):
    """``Box(-1, 1, (3,))`` ``(dx, dy, dzoom)`` (+ a 4th diagnosis component for classification)."""

    name = "continuous"

    def num_actions(self, env) -> int:
        return 3 + (1 if env.task == "classification" else 0)

    def space(self, env, params):
        return spaces.Box(-1.0, 1.0, (self.num_actions(env),), jnp.float32)

    def apply(self, env, state, action, params) -> Move:
        slide = params.slide.select(state.slide_index)
        if env.augment:
            action = dihedral.continuous_to_slide(action, state.orientation)
        stride_px = jnp.round(params.stride * env.tile_size).astype(jnp.int32)
        dx, dy, dz = actions.continuous_deltas(action, stride_px)
        z, x, y = actions.move_and_zoom(slide, state.z, state.x, state.y, dx, dy, dz, env.tile_size, env.n_levels)
        if env.task == "classification":
            diagnosis = actions.continuous_diagnosis(action)
            d = jnp.nan_to_num(jnp.asarray(action, jnp.float32)[3], nan=0.0)
            score = jnp.where(diagnosis < 0, 0.5, (jnp.clip(d, -1.0, 1.0) + 1.0) / 2.0)  # > 0.75 declares tumour
        else:
            diagnosis, score = jnp.full((), -1, jnp.int32), jnp.full((), 0.5, jnp.float32)
        return Move(z, x, y, diagnosis, score.astype(jnp.float32), self._seen(env, state, params, z, x, y))


# ----------------------------------------------------------------------------- observation modes
def view_features(slide, z: jax.Array, x: jax.Array, y: jax.Array) -> jax.Array:
    """Feature vector ``(D,)`` float32 of the view at ``(z, x, y)``: the grid cell whose position is
    nearest the view's top-left corner, ``gx = clip(round(x / stride), 0, gw - 1)`` (likewise
    ``gy``). Exact for grid-aligned views; any other view gets the grid view at most
    ``stride / 2`` px away on each axis (or, at the right/bottom edge, the last grid column/row).
    One gather of ``D`` values."""
    stride = slide.feature_stride
    gw, gh = slide.feature_grid_width[z], slide.feature_grid_height[z]
    gx = jnp.clip((x + stride // 2) // stride, 0, gw - 1)
    gy = jnp.clip((y + stride // 2) // stride, 0, gh - 1)
    row = slide.feature_offset[z] + gy * gw + gx
    return lax.dynamic_index_in_dim(slide.features, row, axis=0, keepdims=False).astype(jnp.float32)


@dataclasses.dataclass(frozen=True)
class ObsMode:
    """Base of the observation modes: ``observe(env, state, params)`` and ``space(env, params)``."""

    name = "base"
    key = "pixels"  # its entry's name in a dict observation
    supports_augment = False
    needs_features = False

    def observe(self, env, state, params):
        raise NotImplementedError

    def space(self, env, params):
        raise NotImplementedError


@dataclasses.dataclass(frozen=True)
class Pixels(ObsMode):
    """The view, ``(T, T, 3)`` uint8 (``as_float``: float32 in ``[0, 1]``), turned with ``augment``."""

    as_float: bool = False
    supports_augment = True

    @property
    def name(self) -> str:
        return "pixels_float" if self.as_float else "pixels"

    def observe(self, env, state, params):
        slide = params.slide.select(state.slide_index)
        pixels = view_pixels(slide, state.z, state.x, state.y, env.tile_size)
        if env.augment:
            pixels = dihedral.orient_pixels(pixels, state.orientation)
        return pixels.astype(jnp.float32) / 255.0 if self.as_float else pixels

    def space(self, env, params):
        t = env.tile_size
        return (
            spaces.Box(0.0, 1.0, (t, t, 3), jnp.float32) if self.as_float else spaces.Box(0, 255, (t, t, 3), jnp.uint8)
        )


@dataclasses.dataclass(frozen=True)
class Features(ObsMode):
    """The ``(D,)`` float32 feature vector of the view (see :func:`view_features`)."""

    name = "features"
    key = "features"
    needs_features = True

    def observe(self, env, state, params):
        slide = params.slide.select(state.slide_index)
        if slide.features is None:
            raise ValueError(
                "obs_mode='features' needs a slide with a feature grid: compute one with "
                "`python -m data_tools features BUNDLE` and make the env from that bundle"
            )
        return view_features(slide, state.z, state.x, state.y)

    def space(self, env, params):
        return spaces.Box(-jnp.inf, jnp.inf, (params.slide.features.shape[-1],), jnp.float32)
