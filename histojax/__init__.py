"""histojax: whole-slide image navigation (pan, zoom in, zoom out) as a pure-JAX RL environment.

env, params = histojax.make("HistoJAX-Easy-v0")
obs, state = env.reset(key, params)
obs, state, reward, terminated, truncated, info = env.step(key, state, action, params)
"""

import histojax.reading.modes  # noqa: F401  (registers the reading modes in the core's mode names; first)
from histojax.adapters.jax import GymnaxV0Wrapper, LogWrapper
from histojax.core.actions import ACTION_NAMES, DOWN, LEFT, RIGHT, STAY, UP, ZOOM_IN, ZOOM_OUT
from histojax.core.env import EnvParams, EnvState, HistoEnv
from histojax.core.slide import SlideArrays
from histojax.loading import load_slide
from histojax.registry import make, register, registered_envs
from histojax.scenarios import Scenario, load_scenario, register_scenario

__version__ = "0.1.0"
__all__ = [
    "ACTION_NAMES",
    "DOWN",
    "EnvParams",
    "EnvState",
    "GymnaxV0Wrapper",
    "HistoEnv",
    "LEFT",
    "LogWrapper",
    "RIGHT",
    "STAY",
    "SlideArrays",
    "UP",
    "ZOOM_IN",
    "ZOOM_OUT",
    "load_slide",
    "make",
    "register",
    "registered_envs",
    "Scenario",
    "load_scenario",
    "register_scenario",
]
