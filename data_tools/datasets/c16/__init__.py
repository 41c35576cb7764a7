"""The true-scale CAMELYON16 benchmark (``python -m data_tools c16``): :mod:`~data_tools.datasets.c16.dataset`
builds it; :mod:`~data_tools.datasets.c16.layout` places the real geometry on each slide (no pixels);
:mod:`~data_tools.datasets.c16.mosaic` paints the pixels from PatchCamelyon patches;
:mod:`~data_tools.datasets.c16.inputs` checks a user's inputs against the two the published tables were built from."""
