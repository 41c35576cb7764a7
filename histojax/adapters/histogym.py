"""HistoGym's API on top of the jitted environment: HistoGym code runs with only its import changed.

    from histojax.adapters.histogym import HistoEnv   # was: from gymhisto import HistoEnv

    env = HistoEnv(img_path, xml_path, tile_size, result_path)
    obs = env.reset()                             # (3, T, T) uint8, channel first like HistoGym
    done = False
    while not done:
        action = env.action_space.sample()
        obs, reward, done, info = env.step(action)
    env.render(mode="save")                       # or "human", "rgb_array"

Same constructor arguments as HistoGym (``img_path`` slide file, ``xml_path`` ASAP XML annotation,
``tile_size`` view px, ``result_path`` folder for saved pictures); the slide is built into a bundle
in the cache (``histojax.sample.cache_dir() / "compat-<sha of slide + xml + tile>"``) the first
time and reused after. Attributes as in HistoGym: ``action_space`` (``.n``, ``.sample()``),
``observation_space``, ``agent_pos`` ``[z, x, y]``, ``max_step`` (2000), ``count``, ``state`` (the
last observation), action codes ``UP=0 … STAY=6``. Defaults follow HistoGym: ``reward="histogym"``
(1000 × tumour fraction − 0.01 at the finest level, with HistoGym's overlap bugs fixed), the fixed
start at the top-left corner of the coarsest level (``random_start=False``), and ``done`` only when
``count`` reaches ``max_step``.

Differences: ``agent_pos`` x, y are the view's top-left corner in px of level ``z`` (0 = coarsest)
rather than DeepZoom tile indices; the zoom levels are histojax's scenarios (``scenario="easy"``
(default), ``"medium"``, ``"hard"``: 3 / 5 / 7 levels over the same magnification range);
``render(mode="rgb_array")`` returns the slide overview with the view drawn on it (the view itself
is ``obs.transpose(1, 2, 0)``); ``"human"`` without a display saves the PNG instead, with a notice.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from histojax.core import actions, spaces
from histojax.core.spaces import NumpyBox as Box  # noqa: F401  (gym-style, numpy)
from histojax.core.spaces import NumpyDiscrete as Discrete

SCENARIOS = {"easy": "HistoJAX-Easy-v0", "medium": "HistoJAX-Medium-v0", "hard": "HistoJAX-Hard-v0"}
RENDER_MODES = ("human", "save", "rgb_array")


def compat_bundle(img_path, xml_path, tile_size: int, progress: bool = True) -> Path:
    """The cached bundle of ``img_path`` (+ ``xml_path``) with ``tile_size`` views for Easy, Medium
    and Hard: ``cache_dir() / f"compat-{sha}"``, built on first use."""
    from histojax.cache import cached_bundle

    return cached_bundle(
        img_path, xml_path, tile_size=int(tile_size), prefix="compat", progress=progress, storage="dense"
    )


def _has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


class HistoEnv:
    """HistoGym's ``HistoEnv`` (gym 0.21 API: ``reset() -> obs``, ``step(a) -> obs, reward, done, info``)
    backed by histojax's jitted environment. See the module doc for arguments and differences."""

    UP, DOWN, LEFT, RIGHT, ZOOM_IN, ZOOM_OUT, STAY = range(7)
    metadata = {"render_modes": list(RENDER_MODES)}

    def __init__(
        self,
        img_path,
        xml_path,
        tile_size,
        result_path,
        *,
        scenario: str = "easy",
        reward: str = "histogym",
        max_step: int = 2000,
        random_start: bool = False,
        seed: int = 0,
        progress: bool = True,
        **make_kwargs,
    ):
        import histojax

        key = str(scenario).lower()
        if key not in SCENARIOS:
            raise ValueError(f"scenario must be one of {tuple(SCENARIOS)}, got {scenario!r}")
        if make_kwargs.get("action_mode", "discrete") != "discrete":
            raise ValueError("the HistoGym API is discrete (7 actions); use histojax.make for continuous actions")
        self.img_path, self.xml_path = img_path, xml_path
        self.tile_size = int(tile_size)
        self.result_path = result_path
        self.scenario = key
        self.max_step = int(max_step)
        Path(result_path).mkdir(parents=True, exist_ok=True)
        self.bundle_path = compat_bundle(img_path, xml_path, self.tile_size, progress=progress)
        self.env, self.params = histojax.make(
            SCENARIOS[key],
            slide=self.bundle_path,
            auto_reset=False,
            reward=reward,
            max_steps_in_episode=self.max_step,
            random_start=random_start,
            **make_kwargs,
        )
        self.n_actions = actions.NUM_DISCRETE_ACTIONS
        self.action_space = spaces.to_numpy(self.env.action_space(self.params), seed=seed)
        self.OBS_W = self.OBS_H = self.tile_size
        self.observation_space = spaces.to_numpy(
            spaces.channel_first(self.env.observation_space(self.params)), seed=seed
        )
        self._key = jax.random.PRNGKey(seed)
        self._reset = jax.jit(self._reset_fn)
        self._step = jax.jit(self._step_fn)
        self._human_notice = False
        self.count = 0
        self.state = None  # the last observation, as in HistoGym
        self.jax_state = None  # histojax's EnvState
        self.agent_pos: list[int] = []
        self.reset()

    # ---------------------------------------------------------------- jitted functions (params as arguments)
    def _reset_fn(self, key, params):
        key, sub = jax.random.split(key)
        obs, state = self.env.reset(sub, params)
        return key, jnp.transpose(obs, (2, 0, 1)), state

    def _step_fn(self, key, state, action, params):
        key, sub = jax.random.split(key)
        obs, state, reward, terminated, truncated, info = self.env.step(sub, state, action, params)
        return key, jnp.transpose(obs, (2, 0, 1)), state, reward, terminated, info

    def _set(self, obs, state) -> None:
        self.jax_state = state  # stays on the device (one jit cache entry)
        obs, pos = jax.device_get((obs, (state.z, state.x, state.y)))
        self.state = np.asarray(obs)
        self.agent_pos = [int(v) for v in pos]

    # ---------------------------------------------------------------- gym API
    def seed(self, seed: int | None = None) -> list[int | None]:
        """Reseed the start positions and the action/observation space samplers."""
        self._key = jax.random.PRNGKey(0 if seed is None else seed)
        self.action_space.seed(seed)
        self.observation_space.seed(seed)
        return [seed]

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start an episode; returns the first observation ``(3, T, T)`` uint8."""
        if seed is not None:
            self.seed(seed)
        self._key, obs, state = self._reset(self._key, self.params)
        self._set(obs, state)
        self.count = 0
        return self.state

    def step(self, action):
        """One step: ``(obs, reward, done, info)``; ``done`` when the reward preset terminates on
        success or ``count`` reaches ``max_step``. Codes outside 0–6 act as STAY."""
        a = np.int32(np.asarray(action).reshape(()))
        key, obs, state, reward, terminated, info = self._step(self._key, self.jax_state, a, self.params)
        self._key = key
        self._set(obs, state)
        reward, terminated, info = jax.device_get((reward, terminated, info))
        self.count += 1
        truncated = self.count >= self.max_step
        done = bool(terminated) or truncated
        z, x, y = self.agent_pos
        info = {
            "agent position: ": f"level {z} :({x},{y})",  # HistoGym's key
            "tumour_fraction": float(info["tumour_fraction"]),
            "success": bool(info["success"]),
            "terminated": bool(terminated),
            "truncated": truncated and not bool(terminated),
        }
        return self.state, float(reward), done, info

    def render(self, mode: str = "save"):
        """``"rgb_array"``: the slide overview with the tumour outline and the current view box,
        ``(H, W, 3)`` uint8. ``"save"``: that picture as a PNG in ``result_path`` (returns its path).
        ``"human"``: show it with matplotlib when a display exists, else save the PNG (one notice)."""
        from histojax.render import render_state

        if mode not in RENDER_MODES:
            raise ValueError(f"render mode must be one of {RENDER_MODES}, got {mode!r}")
        picture = render_state(self.env, self.jax_state, self.params)
        if mode == "rgb_array":
            return picture
        if mode == "human" and _has_display():
            try:
                import matplotlib.pyplot as plt

                plt.imshow(picture)
                plt.title(f"step {self.count}, ({self.agent_pos[0]},{self.agent_pos[1]},{self.agent_pos[2]})")
                plt.pause(0.5)
                plt.draw()
                return None
            except Exception as e:  # no matplotlib / no usable GUI backend: fall back to a file
                reason = f"cannot show a window ({type(e).__name__}: {e})"
        else:
            reason = "no display"
        path = self._save(picture)
        if mode == "human" and not self._human_notice:
            warnings.warn(f"render(mode='human'): {reason}; saving PNGs to {self.result_path} instead", stacklevel=2)
            self._human_notice = True
        return path

    def _save(self, picture: np.ndarray) -> Path:
        from PIL import Image

        z, x, y = self.agent_pos
        path = Path(self.result_path) / f"obs_level_{z}_pos_{x}_{y}_size_{self.tile_size}.png"
        Image.fromarray(picture).save(path)
        return path

    def close(self) -> None:
        pass

    def __repr__(self) -> str:
        return (
            f"HistoEnv({self.img_path!r}, {self.xml_path!r}, {self.tile_size}, {self.result_path!r}, "
            f"scenario={self.scenario!r})"
        )


__all__ = ["Box", "Discrete", "HistoEnv", "compat_bundle"]
