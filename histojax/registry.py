"""Environment ids → scenarios, and ``make``.

Scenarios (all on the same magnification range of the slide; more levels = smaller zoom steps):

==================  ========  ======================  ===================
id                  levels    max_steps_in_episode    zoom per level (R=16)
==================  ========  ======================  ===================
HistoJAX-Easy-v0    3         100                     4×
HistoJAX-Medium-v0  5         200                     2×
HistoJAX-Hard-v0    7         300                     1.59×
==================  ========  ======================  ===================
"""
from __future__ import annotations

import dataclasses

from histojax.env import EnvParams, HistoEnv
from histojax.slide import DEFAULT_MAX_DEVICE_BYTES, load_slide

_REGISTRY: dict[str, dict] = {}
_SLIDES: dict[str, object] = {}  # env id → default slide: a bundle path, or a recipe ``f(spec) -> bundle path``
STATIC_FIELDS = ("tile_size", "action_mode", "obs_mode", "with_position", "reward", "auto_reset", "n_levels")
PARAM_FIELDS = tuple(f.name for f in dataclasses.fields(EnvParams) if f.name != "slide")


def register(env_id: str, slide=None, **spec) -> None:
    """Register a scenario: ``spec`` holds static settings (``n_levels``, ``reward``, …) and
    ``EnvParams`` defaults (``max_steps_in_episode``, …). ``slide`` is the id's default slide when
    ``make`` gets none: a bundle path, or a recipe called with the merged settings that returns
    one (e.g. builds it into the cache on first use); ``None`` means the embedded sample slide."""
    unknown = set(spec) - set(STATIC_FIELDS) - set(PARAM_FIELDS)
    if unknown:
        raise TypeError(f"unknown scenario settings {sorted(unknown)}")
    _REGISTRY[env_id] = dict(spec)
    if slide is None:
        _SLIDES.pop(env_id, None)
    else:
        _SLIDES[env_id] = slide


def registered_envs() -> tuple[str, ...]:
    """All registered environment ids."""
    return tuple(_REGISTRY)


register("HistoJAX-Easy-v0", n_levels=3, max_steps_in_episode=100)
register("HistoJAX-Medium-v0", n_levels=5, max_steps_in_episode=200)
register("HistoJAX-Hard-v0", n_levels=7, max_steps_in_episode=300)


def make(env_id: str, slide=None, verify: bool = True, max_device_bytes: int = DEFAULT_MAX_DEVICE_BYTES,
         **overrides):
    """Make ``(env, params)`` for a registered id.

    ``slide``: a bundle folder (``python -m data_tools build``) or ``None`` for the id's registered
    slide (``register(..., slide=...)``, e.g. a scenario's recipe) or else the embedded sample slide
    (bundles are built on first use). ``overrides``: any static setting
    (``action_mode``, ``obs_mode``, ``with_position``, ``reward``, ``auto_reset``; ``tile_size``
    only for the sample slide, where it selects another cached bundle) or ``EnvParams`` field
    (``max_steps_in_episode``, ``stride``, ``success_threshold``, ``step_cost``,
    ``success_bonus``, ``histogym_scale``, ``dense_weight``, ``random_start``).
    The slide's arrays are put on the device once and returned inside ``params``; a slide
    needing more than ``max_device_bytes`` (default 4 GiB) is refused with a clear error.
    ``verify`` checks every array's SHA-256 against the bundle metadata.
    """
    if env_id not in _REGISTRY:
        raise ValueError(f"unknown environment id {env_id!r}; registered: {', '.join(_REGISTRY)}")
    spec = {**_REGISTRY[env_id], **overrides}
    unknown = set(spec) - set(STATIC_FIELDS) - set(PARAM_FIELDS)
    if unknown:
        raise TypeError(f"make({env_id!r}) got unknown settings {sorted(unknown)}; "
                        f"static: {STATIC_FIELDS}; params: {PARAM_FIELDS}")
    if slide is None and env_id in _SLIDES:
        recipe = _SLIDES[env_id]
        slide = recipe(spec) if callable(recipe) else recipe
    if slide is None:
        from histojax.sample import sample_bundle

        slide = sample_bundle(tile_size=spec.get("tile_size", 128))
    arrays, bundle = load_slide(slide, spec["n_levels"], verify=verify, max_device_bytes=max_device_bytes,
                                features=True if spec.get("obs_mode") == "features" else None)
    tile_size = int(bundle.metadata["tile_size"])
    if spec.get("tile_size", tile_size) != tile_size:
        raise ValueError(f"bundle {slide} was built with tile size {tile_size}; rebuild it with "
                         f"--tile-size {spec['tile_size']} or drop the override")
    static = {k: spec[k] for k in STATIC_FIELDS if k in spec}
    static["tile_size"] = tile_size
    params = EnvParams(slide=arrays, **{k: spec[k] for k in PARAM_FIELDS if k in spec})
    env = HistoEnv(name=env_id, _default_params=params, _bundle=bundle, **static)
    return env, params
