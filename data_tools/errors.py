"""The project's exception types for bad input (slides, annotations, bundles).

Every error names the file it is about and the problem, in one line, so a CLI
can print it without a traceback.
"""

from __future__ import annotations

import os


class HistojaxDataError(Exception):
    """Base class for any bad-input error raised by data_tools or bundle loading."""

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class SlideError(HistojaxDataError):
    """A slide file cannot be read (corrupt, unsupported, too big for the budget)."""


class AnnotationError(HistojaxDataError):
    """An annotation file is malformed, unsafe, or gives nothing usable."""


class BundleError(HistojaxDataError):
    """A slide bundle is missing, incomplete, of another format version, or corrupt."""
