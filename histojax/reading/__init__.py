"""The reading stack: what a reader sees, what it has read, and how a slide is scored from it.

- :mod:`histojax.reading.modes`: the action and observation modes (``base``: the base classes and the
  pan/zoom modes; ``glimpse`` and ``zoom_select``: the reading modes; ``factory``: the names ``make`` takes).
- :mod:`histojax.reading.tables`: the per-slide tables and the seen-views memory the modes keep.
- :mod:`histojax.reading.coarse_map`: the coarse feature map a ``discrete:map`` navigator sees.
- :mod:`histojax.reading.heads`: slide heads (one protocol, one ``load``), scoring a slide from the views read.

The head reward (a wrapper) is :mod:`histojax.adapters.head_reward`.
"""
