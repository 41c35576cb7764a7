"""Atomic writes of every output of the baselines (checkpoints, logs, tables, figures): each file is
written to a temporary sibling, fsync-ed and ``os.replace``-d onto its name
(:func:`data_tools.bundle_format.atomic_file`), so a full disk or a killed run leaves the previous
file or none, never half of one."""
from __future__ import annotations

import contextlib
from pathlib import Path

from data_tools.bundle_format import atomic_file

__all__ = ["atomic_file", "open_text", "save_figure", "write_bytes", "write_text"]


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` atomically onto ``path``; returns the path."""
    path = Path(path)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
    return path


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) atomically onto ``path``; returns the path."""
    return write_bytes(path, text.encode("utf-8"))


@contextlib.contextmanager
def open_text(path, newline: str | None = ""):
    """A text file to write (``newline=""`` for :mod:`csv`) that appears at ``path`` only once the block
    ends without an error."""
    with atomic_file(path) as tmp, open(tmp, "w", newline=newline, encoding="utf-8") as f:
        yield f


def save_figure(fig, path) -> Path:
    """``fig.savefig`` atomically onto ``path`` (the format from its suffix); returns the path."""
    path = Path(path)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format=path.suffix.lstrip(".").lower() or "png")
    return path
