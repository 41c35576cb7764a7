"""HistoEnv: a whole-slide image read like a microscope — pan, zoom in, zoom out — as pure JAX, with gymnax 1.0's
contract::

    obs, state = env.reset(key, params)
    obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)

What the state, the actions, the observations, the rewards, the tasks, the episodes and ``info`` are is the
specification, ``docs/specification.md``; the modes are :mod:`histojax.core.modes`, the rewards
:mod:`histojax.core.rewards`, the augmentation :mod:`histojax.core.augment`, the slide arrays :mod:`histojax.core.slide`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from histojax.core import actions, gymnax_classes, rewards, spaces
from histojax.core import augment as dihedral
from histojax.core.modes import base, factory
from histojax.core.slide import SlideArrays
from histojax.core.views import view_tumour_fraction

try:  # gymnax is optional; code that can ask ``isinstance(env, Environment)`` has it installed
    _GymnaxEnvironment = gymnax_classes.load("environment").Environment  # not all of gymnax
except ImportError:
    _GymnaxEnvironment = object

TASKS = ("detection", "classification")


def sample_index(key: jax.Array, logits: jax.Array) -> jax.Array:
    """An index drawn with probability ``softmax(logits)`` by inverting the cumulative weights:
    one uniform number and a binary search (``jax.random.categorical`` would draw one Gumbel
    number per entry, which dominated the cost of the auto-reset done in every step). With the
    cumulative weights computed beforehand, :func:`sample_row` makes the same draw."""
    cdf = jnp.cumsum(jnp.exp(logits - jnp.max(logits)))
    u = jax.random.uniform(key, (), minval=0.0, maxval=cdf[-1])
    return jnp.minimum(jnp.searchsorted(cdf, u, side="right"), logits.shape[0] - 1).astype(jnp.int32)


def sample_row(key: jax.Array, cdf: jax.Array, row=None) -> jax.Array:
    """:func:`sample_index` from cumulative weights computed beforehand (:func:`histojax.core.slide.start_cdf`):
    ``cdf`` ``(N,)``, or ``(S, N)`` with ``row`` picking one slide's row. The same draw (one uniform
    number, ``searchsorted(side="right")``) as a binary search of ⌈log2(N + 1)⌉ scalar reads, so a
    vmapped reset neither copies the row out nor passes over its N entries."""
    at = (lambda i: cdf[i]) if row is None else (lambda i: cdf[row, i])
    n = cdf.shape[-1]
    u = jax.random.uniform(key, (), minval=0.0, maxval=at(n - 1))

    def halve(_, bounds):  # invariant: cdf[:lo] <= u < cdf[hi:]
        lo, hi = bounds
        mid = (lo + hi) // 2
        right = at(mid) <= u
        return jnp.where(right, mid + 1, lo), jnp.where(right, hi, mid)

    lo, _ = jax.lax.fori_loop(0, max(1, int(n).bit_length()), halve, (jnp.int32(0), jnp.int32(n)))
    return jnp.minimum(lo, n - 1).astype(jnp.int32)


@struct.dataclass
class EnvState:
    """The immutable state of one environment (units in the module doc)."""

    z: jnp.ndarray  # () int32 level of the view, 0 = coarsest, n_levels - 1 = finest
    x: jnp.ndarray  # () int32 view's top-left corner, px of level z
    y: jnp.ndarray  # () int32
    t: jnp.ndarray  # () int32 steps taken this episode
    slide_index: jnp.ndarray  # () int32 which slide of the dataset (0 for one slide)
    orientation: jnp.ndarray = struct.field(default_factory=lambda: jnp.zeros((), jnp.int32))  # () int32 0..7 (augment)
    memory: Any = None  # the action mode's reading memory (None for discrete / continuous)


@struct.dataclass
class EnvParams:
    """Dynamic settings (vmappable). The slide's device arrays travel here, never closed over."""

    slide: SlideArrays  # the slide (or stacked dataset) on the device
    max_steps_in_episode: int = 200  # truncation at this many steps
    stride: float = 1.0  # move length in view widths
    success_threshold: float = 0.5  # tumour fraction of the finest view that counts as found
    step_cost: float = 0.01  # paid every step
    success_bonus: float = 10.0  # paid on success ("sparse", "dense")
    histogym_scale: float = 1000.0  # "histogym": reward per unit tumour fraction at the finest level
    dense_weight: float = 1.0  # "dense": weight of the potential difference
    random_start: bool = True  # False: HistoGym's fixed start at the top-left, coarsest level
    start_level: int = 0  # navigation modes: the level episodes start at (0 = coarsest, HistoGym's;
    # -1 = finest; clipped to the levels), centred on the coarsest start view
    diagnosis_reward: float = 1.0  # task="classification": +this for a right diagnosis, -this for a wrong one
    mode_data: Any = None  # the action mode's per-slide tables (ActionMode.prepare); None for navigation


@dataclasses.dataclass(frozen=True, eq=False)
class HistoEnv(_GymnaxEnvironment):
    """A slide-navigation environment. Static (hashable) settings are fields; see the module doc.

    **Equality and hash** (what ``jax.jit(..., static_argnums=env)`` keys its compiled programs
    on): two envs are equal when their settings are equal *and* they hold the very same default
    params and bundle objects. With ``params=None`` a jitted function reads the slide and the
    settings from ``env.default_params``, so envs with different data must never compare equal.
    gymnax's own envs compare by identity; histojax compares the data by identity and the
    settings by value, so ``dataclasses.replace(env, ...)`` of one env still shares compiled
    programs while two ``make`` calls (or a deepcopy) never do. A digest of the default params
    would also be sound but would copy the whole slide (up to ``max_device_bytes``) to the host to
    hash it; the params are immutable (a frozen pytree of JAX arrays), so identity of the object
    is identity of the content, at no cost. The ids are of objects the env keeps alive, so none can
    be reused by other data while the env, or a compiled program keyed on it, exists.
    """

    n_levels: int
    tile_size: int = 128
    action_mode: Any = "discrete"  # a name in histojax.core.modes.factory.ACTION_MODES or an ActionMode object
    obs_mode: Any = "pixels"  # a name in histojax.core.modes.factory.OBS_MODES or an ObsMode object
    with_position: bool = False
    reward: str = "dense"
    auto_reset: bool = True
    final_observation: bool = True
    task: str = "detection"
    augment: bool = False
    step_obs: bool = False  # reading modes: a step observes what changed; per-episode tables apart
    name: str = "HistoJAX-v0"
    _default_params: Any = dataclasses.field(default=None, compare=False, hash=False, repr=False)
    _bundle: Any = dataclasses.field(default=None, compare=False, hash=False, repr=False)
    _bundles: Any = dataclasses.field(default=(), compare=False, hash=False, repr=False)  # one per slide

    def _identity(self) -> tuple:
        settings = tuple(getattr(self, f.name) for f in dataclasses.fields(self) if f.compare)
        data = tuple(id(getattr(self, f.name)) for f in dataclasses.fields(self) if not f.compare)
        return type(self), settings, data

    def __eq__(self, other) -> bool:
        if not isinstance(other, HistoEnv):
            return NotImplemented
        return self._identity() == other._identity()

    def __hash__(self) -> int:
        return hash(self._identity())

    def __post_init__(self):
        action, observation = self.action, self.observation  # unknown names raise here
        if self.reward not in rewards.PRESETS:
            raise ValueError(f"reward must be one of {rewards.PRESETS}, got {self.reward!r}")
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {self.task!r}")
        if self.augment and not observation.supports_augment:
            raise ValueError(
                "augment=True turns the view's pixels; a feature vector cannot be turned. "
                "Use obs_mode='pixels' (or 'pixels_float'), or compute features of turned views"
            )
        if self.augment and not action.supports_augment:
            raise ValueError(f"augment=True cannot turn action_mode={action.name!r}; use 'discrete' or 'continuous'")
        action.validate(self)

    # ----------------------------------------------------------------- the modes (histojax.core.modes.base)
    @property
    def action(self) -> base.ActionMode:
        """The action mode object ``action_mode`` names."""
        return factory.action_mode(self.action_mode)

    @property
    def observation(self) -> base.ObsMode:
        """The observation mode object ``obs_mode`` names."""
        return factory.obs_mode(self.obs_mode)

    # ----------------------------------------------------------------- gymnax API
    @property
    def default_params(self) -> EnvParams:
        """The parameters ``make`` returned (slide arrays on the device, scenario defaults)."""
        return self._default_params

    @property
    def bundles(self) -> tuple:
        """The host bundles (:class:`data_tools.bundle_files.reading.Bundle`: metadata, thumbnails, levels coarsest
        first) of the env's slides, one per slide, read-only: for rendering and inspection. Empty for an env
        made without data (``histojax.adapters.gymnasium.settings_only``). Copy an env with one change with
        ``dataclasses.replace(env, setting=value)``; its bundles go with it."""
        return tuple(self._bundles) or (() if self._bundle is None else (self._bundle,))

    @property
    def num_actions(self) -> int:
        """Discrete: the number of actions (7, +2 diagnosis actions for classification; see the mode);
        continuous: the Box size 3 (or 4)."""
        return self.action.num_actions(self)

    def action_space(self, params: EnvParams | None = None):
        """The action mode's space, e.g. ``Discrete(7)`` or ``Box(-1, 1, (3,), float32)``."""
        return self.action.space(self, self.default_params if params is None else params)

    def observation_space(self, params: EnvParams | None = None):
        """The observation mode's space (view pixels or features), or a Dict with the position and the
        action mode's memory entries when there are any."""
        params = self.default_params if params is None else params
        view = self.observation.space(self, params)
        extra = self._extra_spaces(params)
        return spaces.Dict({self.observation.key: view, **extra}) if extra else view

    def state_space(self, params: EnvParams | None = None):
        """A ``Dict`` space of the ``EnvState`` fields, with their bounds as gymnax's envs give them:
        ``z`` ``Discrete(n_levels)``; ``x``, ``y`` (px of level ``z``) ``Box`` int32 from 0 (or the
        smallest ``level size - tile_size`` when a level is narrower than a view) to the largest
        ``level size - tile_size`` of any level and slide; ``t`` ``Discrete(max_steps_in_episode + 1)``
        (with ``auto_reset=False``, a state stepped past its episode's end is outside);
        ``slide_index`` ``Discrete(num_slides)``; ``orientation`` ``Discrete(8)``. The action mode's
        reading ``memory`` (a pytree, ``None`` for most modes) is not described. ``contains`` takes an
        ``EnvState`` (fields read by attribute, as gymnax's ``Dict`` does)."""
        params = self.default_params if params is None else params
        s = params.slide
        spare_x = jax.device_get(s.level_width).astype("int64") - self.tile_size
        spare_y = jax.device_get(s.level_height).astype("int64") - self.tile_size

        def corner(spare):
            return spaces.Box(min(0, int(spare.min())), max(0, int(spare.max())), (), jnp.int32)

        return spaces.Dict(
            {
                "z": spaces.Discrete(self.n_levels),
                "x": corner(spare_x),
                "y": corner(spare_y),
                "t": spaces.Discrete(int(params.max_steps_in_episode) + 1),
                "slide_index": spaces.Discrete(s.num_slides),
                "orientation": spaces.Discrete(dihedral.NUM_ORIENTATIONS),
            }
        )

    def episode_tables(self, params: EnvParams | None = None) -> dict:
        """What is fixed for each slide during an episode, ``{name: (S, ...) array}`` for ``S`` slides, which
        a policy indexes with the observation's ``"slide"`` entry inside its forward pass (so a rollout
        stores only the small step observation). ``{}`` for modes without any. With ``step_obs=True``
        (the ``-v2`` ids) the ``glimpse`` observation holds none of it: see :mod:`histojax.reading.modes.glimpse`."""
        params = self.default_params if params is None else params
        return self.action.episode_tables(self, params)

    def _extra_spaces(self, params) -> dict:
        extra = {"position": spaces.Box(0.0, 1.0, (3,), jnp.float32)} if self.with_position else {}
        return {**extra, **self.action.memory_space(self, params)}

    def reset(self, key: jax.Array, params: EnvParams | None = None):
        """Start an episode: ``(obs, state)``."""
        params = self.default_params if params is None else params
        return self.reset_env(key, params)

    def step(self, key: jax.Array, state: EnvState, action, params: EnvParams | None = None):
        """One step with auto-reset (unless ``auto_reset=False``):
        ``(obs, state, reward, terminated, truncated, info)``. The only place episodes restart."""
        params = self.default_params if params is None else params
        key_reset, _ = jax.random.split(key)
        state_st, reward, terminated, truncated, info = self._transition(state, action, params)
        if not self.auto_reset:
            obs = self.get_obs(state_st, params)
            return obs, state_st, reward, terminated, truncated, {**info, "final_observation": obs}
        state_re = self._reset_state(key_reset, params, with_memory=False)
        done = jnp.logical_or(terminated, truncated)
        state = jax.tree.map(lambda a, b: jnp.where(done, a, b), state_re, state_st.replace(memory=None))
        if state_st.memory is not None:  # the mode starts its memory's new episode (see ActionMode.auto_reset_memory)
            state = state.replace(memory=self.action.auto_reset_memory(self, done, state_st.memory, state, params))
        obs = self.get_obs(state, params)  # one observation, of the state kept after the auto-reset
        if self.final_observation:  # the stepped state's, for info; under jit it costs nothing unless used
            final = self.get_obs(state_st, params)
        else:  # the key stays, without a wrong view
            final = jax.tree.map(lambda a: jnp.zeros((0,), a.dtype), obs)
        return obs, state, reward, terminated, truncated, {**info, "final_observation": final}

    # ----------------------------------------------------------------- dynamics
    def reset_env(self, key: jax.Array, params: EnvParams):
        """A fresh episode at the coarsest level, on a random tissue view or the top-left corner;
        for a dataset, of a slide drawn by its weight: ``(obs, state)``."""
        state = self._reset_state(key, params)
        return self.get_obs(state, params), state

    def _reset_state(self, key: jax.Array, params: EnvParams, with_memory: bool = True) -> EnvState:
        """The start state of :meth:`reset_env`, without the observation. Private: :meth:`step`'s
        auto-reset needs the new state alone, to choose between it and the stepped state before
        extracting any view (one view per step with ``final_observation=False``); it starts the mode's
        memory itself (``with_memory=False``: ``memory`` is ``None``)."""
        key_slide, key = jax.random.split(key)
        if params.slide.num_slides > 1:
            slide_index = sample_index(key_slide, params.slide.slide_logits)
        else:
            slide_index = jnp.zeros((), jnp.int32)
        width = params.slide.start_logits.shape[-1]
        if params.slide.start_cdf is None:
            index = sample_index(key, params.slide.select(slide_index).start_logits.reshape(-1))
        else:  # the slide's row of the cumulative weights is searched in place, never copied out
            cdf = params.slide.start_cdf
            index = sample_row(key, cdf, slide_index if cdf.ndim > 1 else None)
        y0, x0 = jnp.divmod(index, width)
        start = jnp.asarray(params.random_start)
        zero = jnp.zeros((), jnp.int32)
        if self.augment:  # a static setting: without it the keys (and trajectories) are unchanged
            key, key_orientation = jax.random.split(key)
            orientation = jax.random.randint(key_orientation, (), 0, dihedral.NUM_ORIENTATIONS, jnp.int32)
        else:
            orientation = zero
        x0 = jnp.where(start, x0, 0).astype(jnp.int32)
        y0 = jnp.where(start, y0, 0).astype(jnp.int32)
        z = zero
        if isinstance(self.action, base.Navigation):  # static: the reading modes' memories start at the coarsest level
            z, x0, y0 = self._start_view(params, slide_index, x0, y0)
        state = EnvState(
            z=z,
            x=x0,
            y=y0,
            t=zero,
            slide_index=slide_index,
            orientation=orientation,
        )
        return state.replace(memory=self.action.init_memory(self, state, params)) if with_memory else state

    def _start_view(self, params: EnvParams, slide_index, x0, y0):
        """``(z, x, y)`` of the start at level ``params.start_level`` (negative: from the finest; clipped),
        centred on the coarsest-level view at ``(x0, y0)`` (px of level 0, as a zoom keeps the centre) and
        clamped inside the level. Level 0 returns ``(0, x0, y0)`` unchanged."""
        n = self.n_levels
        level = jnp.asarray(params.start_level, jnp.int32)
        z = jnp.clip(jnp.where(level < 0, n + level, level), 0, n - 1).astype(jnp.int32)
        slide = params.slide.select(slide_index)
        ratio = slide.downsample[0] / slide.downsample[z]
        half = self.tile_size / 2.0
        x = jnp.round((x0 + half) * ratio - half).astype(jnp.int32)
        y = jnp.round((y0 + half) * ratio - half).astype(jnp.int32)
        x, y = actions.clamp_position(slide, z, x, y, self.tile_size)
        at_zero = z == 0
        return z, jnp.where(at_zero, x0, x).astype(jnp.int32), jnp.where(at_zero, y0, y).astype(jnp.int32)

    def step_env(self, key: jax.Array, state: EnvState, action, params: EnvParams):
        """One step without auto-reset: ``(obs, state, reward, terminated, truncated, info)``
        (``info`` without ``final_observation``, which :meth:`step` adds)."""
        new_state, reward, terminated, truncated, info = self._transition(state, action, params)
        return self.get_obs(new_state, params), new_state, reward, terminated, truncated, info

    def _transition(self, state: EnvState, action, params: EnvParams):
        """The dynamics without the observation: ``(state, reward, terminated, truncated, info)``.
        The action mode picks the next view (and diagnosis); the task scores it. Private: shared by
        :meth:`step_env` and :meth:`step`, which observes only the state it keeps after auto-reset."""
        slide, t = params.slide.select(state.slide_index), self.tile_size
        move = self.action.apply(self, state, action, params)
        z, x, y = move.z, move.x, move.y
        fraction = view_tumour_fraction(slide, z, x, y, t)
        extra = {}
        if self.task == "detection":  # find the tumour
            prev_fraction = view_tumour_fraction(slide, state.z, state.x, state.y, t)
            success = (z == self.n_levels - 1) & (fraction >= params.success_threshold)
            reward = rewards.reward(self.reward, params, fraction, z, prev_fraction, state.z, success, self.n_levels)
            terminated = success if rewards.terminates_on_success(self.reward) else jnp.zeros((), bool)
        else:  # classification: declaring a diagnosis ends the episode
            declared = move.diagnosis >= 0
            success = declared & (move.diagnosis == slide.slide_label)
            reward = rewards.classification_reward(params, declared, success)
            terminated = declared
            extra = {"score": move.score, "declared": declared}
        new_state = EnvState(
            z=z,
            x=x,
            y=y,
            t=state.t + 1,
            slide_index=state.slide_index,
            orientation=state.orientation,
            memory=move.memory,
        )
        truncated = jnp.logical_and(new_state.t >= params.max_steps_in_episode, jnp.logical_not(terminated))
        truncated = jnp.logical_or(truncated, self.action.budget_spent(self, new_state, params)) & ~terminated
        info = {
            "tumour_fraction": fraction,
            "success": success,
            "discount": 1.0 - terminated.astype(jnp.float32),
            "terminated": terminated,
            "truncated": truncated,
            "steps": new_state.t,
            **extra,
            **self.action.reading_info(self, new_state, params),
        }
        return new_state, reward.astype(jnp.float32), terminated, truncated, info

    def get_obs(self, state: EnvState, params: EnvParams | None = None, key: jax.Array | None = None):
        """The observation of ``state`` (see the module doc for modes and units); ``key`` is unused
        (gymnax's signature)."""
        params = self.default_params if params is None else params
        obs = self.observation.observe(self, state, params)
        extra = {}
        if self.with_position:
            extra["position"] = self._position(state, params.slide.select(state.slide_index))
        extra.update(self.action.memory_obs(self, state, params))
        return {self.observation.key: obs, **extra} if extra else obs

    def is_truncated(self, state: EnvState, params: EnvParams) -> jax.Array:
        """True when the episode has reached ``params.max_steps_in_episode`` steps (bool scalar)."""
        return state.t >= params.max_steps_in_episode

    def _position(self, state: EnvState, slide: SlideArrays):
        """``(x_centre / W_z, y_centre / H_z, z / (n_levels - 1))`` float32 in ``[0, 1]``."""
        half = self.tile_size / 2.0
        position = jnp.stack(
            [
                (state.x + half) / slide.level_width[state.z],
                (state.y + half) / slide.level_height[state.z],
                state.z / max(self.n_levels - 1, 1),
            ]
        ).astype(jnp.float32)
        return dihedral.orient_position(position, state.orientation) if self.augment else position

    # ----------------------------------------------------------------- host-side helpers
    def render(self, state: EnvState, params: EnvParams | None = None):
        """RGB uint8 ``(H, W, 3)`` numpy picture: slide thumbnail, tumour outline, the current view box."""
        from histojax.render import render_state

        return render_state(self, state, self.default_params if params is None else params)

    def reward_range(self, params: EnvParams | None = None) -> tuple[float, float]:
        """Documented ``(min, max)`` reward for these parameters."""
        params = self.default_params if params is None else params
        if self.task == "classification":
            return rewards.classification_range(params)
        return rewards.reward_range(self.reward, params)
