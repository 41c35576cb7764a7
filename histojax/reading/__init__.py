"""The reading stack, on top of the env core (:mod:`histojax.core`): how a slide is read and scored.

- :mod:`histojax.reading.modes`: the reading modes (``glimpse``, ``zoom_select``); importing the package registers
  them in the core's mode names (:mod:`histojax.core.modes.factory`).
- :mod:`histojax.reading.tables`: the reading modes' per-slide tables (cells over finest views, view features).
- :mod:`histojax.reading.coarse_map`: the coarse feature map a ``discrete:map`` navigator sees.
- :mod:`histojax.reading.heads`: slide heads (one protocol, one ``load``), scoring a slide from the views read.
- :mod:`histojax.reading.head_reward`: SASHA's reward through a slide head, a gymnax-style reward wrapper.

The navigation and observation modes every env uses, and the seen-views memory behind ``fraction_read``, are the
core's (:mod:`histojax.core.modes`, :mod:`histojax.core.seen_views`).
"""
