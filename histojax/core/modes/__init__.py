"""The env core's action and observation modes: ``base`` (the base classes, the pan/zoom navigation modes
``Discrete`` / ``Continuous``, the observation modes ``Pixels`` / ``Features``) and ``factory`` (the mode names
``make`` takes: a registry the reading stack, :mod:`histojax.reading.modes`, adds ``glimpse`` and ``zoom_select`` to)."""
