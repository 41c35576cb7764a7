"""The env core: the pure, jittable step and what it is made of, apart from the host tools.

- :mod:`histojax.core.modes`: the action and observation modes (``base``: the base classes, the pan/zoom
  navigation modes, the observation modes; ``factory``: the mode names ``make`` takes, a registry the reading
  stack adds its modes to).
- :mod:`histojax.core.seen_views`: the finest-level views, the tissue views and the seen-views memory that
  ``fraction_read`` and the ``visited`` map count.

Nothing here imports :mod:`histojax.reading` (``tests/project/test_import_graph.py`` holds it): the reading stack sits on
top of the core and plugs its modes and its coarse map in when it is imported.
"""
