"""Synthetic slides on real CAMELYON16 geometry (synthetic pixels, real tumour and tissue outlines):
:mod:`~data_tools.datasets.synth.dataset` makes the small semi-synthetic slides and their dataset
(``python -m data_tools synth``); :mod:`~data_tools.datasets.synth.large_slide` one gigapixel test slide
(``python -m data_tools synth-large``)."""
