"""Action and observation modes: ``base`` (the base classes, pan/zoom navigation, the observation modes),
``glimpse`` and ``zoom_select`` (the reading modes), ``factory`` (the mode names ``make`` takes)."""
