"""Slide files: open a whole-slide image file and read its pyramid levels as 8-bit RGB.

One module per job (the pattern of TRIDENT's ``wsi_objects``): :mod:`~data_tools.slide_files.open` is the public entry
(:func:`~data_tools.slide_files.open.open_slide` opens any slide file, picking the reader); :mod:`.base` holds what
every reader shares (the ``SlideReader`` base class, levels, pyramid checks, the summary); :mod:`.tiff` reads SVS / pyramidal TIFF / OME-TIFF with
tifffile; :mod:`.dicom` DICOM WSI; :mod:`.openslide` the formats OpenSlide reads, with :mod:`.mirax` checking a MIRAX
slide before OpenSlide sees it; :mod:`.limits` the size limits every reader applies.

"Reader" elsewhere in histojax means a reading policy (:mod:`baselines.reading`); here the classes are named for the
file they open (``SlideReader`` and its TIFF / DICOM / OpenSlide subclasses).
"""
