"""Mode names → mode objects: the one place the strings users pass to ``make(..., action_mode=...,
obs_mode=...)`` (and trainers' JSON configs hold) are resolved.

The names are a registry, filled from two floors without an upward import. This module registers the env core's
modes (``discrete``, ``continuous`` and their ``:memory`` / ``:map`` forms; ``pixels``, ``pixels_float``,
``features``); the reading stack registers its own (``glimpse[:LEVEL]``, ``zoom_select[:K]``) with
:func:`register_action_mode` when :mod:`histojax.reading.modes` is imported, and ``histojax/__init__.py`` imports it,
so every ``import histojax`` (and so every ``import histojax.core...``, which runs it first) sees every name. The core
never imports ``histojax.reading``; the reading modes import only the core's base classes
(:mod:`histojax.core.modes.base`), so there is no import circle. A mode of your own is registered the same way.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

from histojax.core.modes.base import ActionMode, Continuous, Discrete, Features, ObsMode, Pixels

# name -> build(arg) -> ActionMode, where arg is the text after "name:" ("" without one); insertion order is the
# order error messages list the names in
ACTION_MODES: dict[str, Callable[[str], ActionMode]] = {}
ACTION_FORMS: list[str] = []  # the ":"-forms of the registered names ("discrete:memory", "glimpse:LEVEL", ...)
OBS_MODES: dict[str, Callable[[], ObsMode]] = {
    "pixels": Pixels,
    "pixels_float": lambda: Pixels(as_float=True),
    "features": Features,
}


def register_action_mode(name: str, build: Callable[[str], ActionMode], forms: tuple[str, ...] = ()) -> None:
    """Make ``action_mode=name`` (and ``"name:ARG"``) resolve to ``build(arg)``: ``arg`` is the text after the
    ``:`` (``""`` without one); ``build`` raises ``ValueError`` (one line) for an ``arg`` it does not take.
    ``forms``: the ``":"``-forms it takes, as error messages list them (e.g. ``("glimpse:LEVEL",)``). Registering
    a name again replaces its builder."""
    ACTION_MODES[name] = build
    ACTION_FORMS.extend(f for f in forms if f not in ACTION_FORMS)


def whole_number_arg(cls: type, field: str, name: str) -> Callable[[str], ActionMode]:
    """A builder for :func:`register_action_mode`: ``cls()``, or with ``"name:N"`` ``cls(**{field: N})`` (``N`` a
    whole number)."""

    def build(arg: str) -> ActionMode:
        if not arg:
            return cls()
        if not arg.isdigit():
            raise ValueError(f"action_mode {name + ':' + arg!r}: the part after ':' must be a whole number")
        return dataclasses.replace(cls(), **{field: int(arg)})

    return build


def _navigation(cls: type) -> Callable[[str], ActionMode]:
    """The builder of a pan/zoom mode: ``":memory"`` keeps the coarse visited map and the position in the
    observation, ``":map"`` also a coarse map (``make(..., map_feature=ENTRY)`` or ``map_head=HEAD``)."""

    def build(arg: str) -> ActionMode:
        if arg not in ("", "memory", "map"):
            raise _unknown(f"{cls.name}:{arg}")
        return dataclasses.replace(cls(), memory=True, coarse_map=arg == "map") if arg else cls()

    return build


def _unknown(mode) -> ValueError:
    return ValueError(f"action_mode must be one of {tuple(ACTION_MODES)} (or {', '.join(ACTION_FORMS)}), got {mode!r}")


register_action_mode("discrete", _navigation(Discrete))
register_action_mode("continuous", _navigation(Continuous))
ACTION_FORMS.extend(["discrete:memory", "continuous:memory", "discrete:map", "continuous:map"])


def action_mode(mode) -> ActionMode:
    """The action mode object for a name in :data:`ACTION_MODES` (or an ``ActionMode`` as it is).
    ``"discrete:memory"`` / ``"continuous:memory"`` are the pan/zoom modes with ``memory=True`` (the
    coarse visited map and the position in the observation), ``"discrete:map"`` / ``"continuous:map"`` the
    same plus a coarse map of one feature entry (``make(..., map_feature=ENTRY)``; its builder is
    :func:`histojax.core.seen_views.coarse_maps`); the reading stack's ``"glimpse:L"`` and ``"zoom_select:K"`` set the
    glimpse level / the number of children a side. Strings, so a trainer's JSON config can name them."""
    if isinstance(mode, ActionMode):
        return mode
    name, sep, arg = str(mode).partition(":")
    if name not in ACTION_MODES or (sep and not arg):
        raise _unknown(mode)
    return ACTION_MODES[name](arg)


def obs_mode(mode) -> ObsMode:
    """The observation mode object for a name in :data:`OBS_MODES` (or an ``ObsMode`` as it is)."""
    if isinstance(mode, ObsMode):
        return mode
    if mode not in OBS_MODES:
        raise ValueError(f"obs_mode must be one of {tuple(OBS_MODES)}, got {mode!r}")
    return OBS_MODES[mode]()
