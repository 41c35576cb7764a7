"""Mode names → mode objects: the one place the strings users pass to ``make(..., action_mode=...,
obs_mode=...)`` (and trainers' JSON configs hold) are resolved. It imports every mode; the modes
import only their base classes (:mod:`histojax.reading.modes.base`), so there is no import circle.
"""
from __future__ import annotations

import dataclasses

from histojax.reading.modes.glimpse import Glimpse
from histojax.reading.modes.base import ActionMode, Continuous, Discrete, Features, ObsMode, Pixels
from histojax.reading.modes.zoom_select import ZoomSelect

ACTION_MODES = {"discrete": Discrete, "continuous": Continuous, "glimpse": Glimpse, "zoom_select": ZoomSelect}
OBS_MODES = {"pixels": Pixels, "pixels_float": lambda: Pixels(as_float=True), "features": Features}


def action_mode(mode) -> ActionMode:
    """The action mode object for a name in :data:`ACTION_MODES` (or an ``ActionMode`` as it is).
    ``"glimpse:L"`` and ``"zoom_select:K"`` set the glimpse level / the number of children a side;
    ``"discrete:memory"`` / ``"continuous:memory"`` are the pan/zoom modes with ``memory=True`` (the
    coarse visited map and the position in the observation), ``"discrete:map"`` / ``"continuous:map"`` the
    same plus a coarse map of one feature entry (``make(..., map_feature=ENTRY)``; :mod:`histojax.reading.coarse_map`).
    Strings, so a trainer's JSON config can name them."""
    if isinstance(mode, ActionMode):
        return mode
    name, sep, arg = str(mode).partition(":")
    navigation = name in ("discrete", "continuous")
    if name not in ACTION_MODES or (sep and not arg) or (arg and not navigation and name not in ("glimpse", "zoom_select")) \
            or (arg and navigation and arg not in ("memory", "map")):
        raise ValueError(f"action_mode must be one of {tuple(ACTION_MODES)} (or glimpse:LEVEL, zoom_select:K, "
                         f"discrete:memory, continuous:memory, discrete:map, continuous:map), got {mode!r}")
    obj = ACTION_MODES[name]()
    if navigation and arg:
        return dataclasses.replace(obj, memory=True, coarse_map=arg == "map")
    if arg:
        if not arg.isdigit():
            raise ValueError(f"action_mode {mode!r}: the part after ':' must be a whole number")
        obj = dataclasses.replace(obj, **{"level" if name == "glimpse" else "k": int(arg)})
    return obj


def obs_mode(mode) -> ObsMode:
    """The observation mode object for a name in :data:`OBS_MODES` (or an ``ObsMode`` as it is)."""
    if isinstance(mode, ObsMode):
        return mode
    if mode not in OBS_MODES:
        raise ValueError(f"obs_mode must be one of {tuple(OBS_MODES)}, got {mode!r}")
    return OBS_MODES[mode]()
