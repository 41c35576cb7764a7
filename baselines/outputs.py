"""Atomic writes of every output of the baselines (checkpoints, logs, tables, figures): each file is
written to a temporary sibling, fsync-ed and ``os.replace``-d onto its name
(:func:`data_tools.bundle_files.writes.atomic_file`), so a full disk or a killed run leaves the previous
file or none, never half of one. :func:`staged` does the same for a set of files as a whole (a
training run's ``log.csv``, ``log.json``, ``curve.png``, ``params.msgpack``, ``config.json``): all are
written to temporary siblings first and renamed into place only once every one is whole, so a run that
fails while writing keeps the previous run's files side by side, not a new log beside old parameters."""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path

from data_tools.bundle_files.writes import atomic_file

__all__ = ["Stage", "atomic_file", "open_text", "save_figure", "staged", "write_bytes", "write_text"]


def _named(e: OSError, path: Path) -> OSError:
    """``e`` with ``path`` as its file name (a failed ``write`` names none: "No space left on device")."""
    if e.filename is not None:
        return e
    return OSError(e.errno, e.strerror or str(e), str(path))


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` atomically onto ``path``; returns the path. An error names ``path``."""
    path = Path(path)
    try:
        with atomic_file(path) as tmp, open(tmp, "wb") as f:
            f.write(data)
    except OSError as e:
        raise _named(e, path) from e
    return path


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) atomically onto ``path``; returns the path."""
    return write_bytes(path, text.encode("utf-8"))


@contextlib.contextmanager
def open_text(path, newline: str | None = ""):
    """A text file to write (``newline=""`` for :mod:`csv`) that appears at ``path`` only once the block
    ends without an error."""
    path = Path(path)
    try:
        with atomic_file(path) as tmp, open(tmp, "w", newline=newline, encoding="utf-8") as f:
            yield f
    except OSError as e:
        raise _named(e, path) from e


def save_figure(fig, path) -> Path:
    """``fig.savefig`` atomically onto ``path`` (the format from its suffix); returns the path."""
    path = Path(path)
    try:
        with atomic_file(path) as tmp:
            fig.savefig(tmp, format=path.suffix.lstrip(".").lower() or "png")
    except OSError as e:
        raise _named(e, path) from e
    return path


class Stage:
    """Files written as a whole (see :func:`staged`): each ``write_*`` goes to a temporary sibling
    ``.NAME.staged-XXXXXXXX.SUFFIX`` of its path; :meth:`commit` renames them all into place."""

    def __init__(self):
        self.pending: list[tuple[Path, Path]] = []  # (temporary, final)

    def path(self, path) -> Path:
        """A temporary sibling of ``path`` (same suffix, so a figure keeps its format) to write
        ``path``'s content to; it is moved onto ``path`` at :meth:`commit`."""
        path = Path(path)
        tmp = path.with_name(f".{path.stem}.staged-{uuid.uuid4().hex[:8]}{path.suffix}")
        self.pending.append((tmp, path))
        return tmp

    @contextlib.contextmanager
    def writing(self, path):
        """Yield the temporary path of ``path``; an OSError in the block names ``path``."""
        tmp = self.path(path)
        try:
            yield tmp
        except OSError as e:
            raise _named(e, Path(path)) from e

    def write_bytes(self, path, data: bytes) -> Path:
        """Stage ``data`` for ``path``; returns ``path``."""
        with self.writing(path) as tmp, open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        return Path(path)

    def write_text(self, path, text: str) -> Path:
        """Stage ``text`` (UTF-8) for ``path``; returns ``path``."""
        return self.write_bytes(path, text.encode("utf-8"))

    @contextlib.contextmanager
    def open_text(self, path, newline: str | None = ""):
        """A text file staged for ``path`` (``newline=""`` for :mod:`csv`)."""
        with self.writing(path) as tmp, open(tmp, "w", newline=newline, encoding="utf-8") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())

    def commit(self) -> None:
        """Rename every staged file onto its path (in the order staged)."""
        for tmp, path in self.pending:
            try:
                os.replace(tmp, path)
            except OSError as e:
                raise _named(e, path) from e
        self.pending = []

    def discard(self) -> None:
        """Remove every staged file not yet renamed."""
        for tmp, _ in self.pending:
            tmp.unlink(missing_ok=True)
        self.pending = []


@contextlib.contextmanager
def staged():
    """A :class:`Stage`: the files written through it appear at their paths together when the block ends
    without an error; on an error (a full disk: the error names the file) none of them is replaced and no
    temporary file is left."""
    stage = Stage()
    try:
        yield stage
        stage.commit()
    finally:
        stage.discard()
