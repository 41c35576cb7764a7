"""Offline tools (numpy, tifffile, shapely): slide files and annotations → slide bundles.

Data flows one way: files → data_tools → bundle on disk → histojax device arrays.
"""

from data_tools.errors import AnnotationError, BundleError, HistojaxDataError, SlideError

__all__ = ["AnnotationError", "BundleError", "HistojaxDataError", "SlideError"]
