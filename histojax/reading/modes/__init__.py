"""The reading stack's action modes: ``glimpse`` (SASHA style: pick cells of a low-magnification grid) and
``zoom_select`` (RLogist style: zoom into one of ``k × k`` children). Both subclass the env core's
:class:`histojax.core.modes.base.ActionMode`.

Importing this package registers them, with their ``glimpse:LEVEL`` / ``zoom_select:K`` forms, in the core's mode
names (:func:`histojax.core.modes.factory.register_action_mode`), and plugs the coarse map of the ``discrete:map`` /
``continuous:map`` navigators (:func:`histojax.reading.coarse_map.coarse_maps`) into the core
(:func:`histojax.core.seen_views.register_coarse_map`). ``histojax/__init__.py`` imports it, so every
``import histojax`` knows every mode name, while the core imports nothing from ``histojax.reading``.
"""

from __future__ import annotations

from histojax.core import seen_views
from histojax.core.modes import factory
from histojax.reading.modes.glimpse import Glimpse
from histojax.reading.modes.zoom_select import ZoomSelect


def _coarse_maps(env, params, bundles, feature, level=-3, head=None):
    """:func:`histojax.reading.coarse_map.coarse_maps`, imported when a ``:map`` navigator is made (it loads the
    slide heads, which ``import histojax`` does not need)."""
    from histojax.reading.coarse_map import coarse_maps

    return coarse_maps(env, params, bundles, feature, level, head=head)


factory.register_action_mode("glimpse", factory.whole_number_arg(Glimpse, "level", "glimpse"), ("glimpse:LEVEL",))
factory.register_action_mode(
    "zoom_select", factory.whole_number_arg(ZoomSelect, "k", "zoom_select"), ("zoom_select:K",)
)
seen_views.register_coarse_map(_coarse_maps)
