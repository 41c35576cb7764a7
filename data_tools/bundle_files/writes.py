"""Safe writes of bundles, datasets and run outputs: every file written to a temporary sibling, fsync-ed and renamed
into place (:func:`atomic_file`, :func:`save_array`, :func:`write_json`); whole folders built in a marked hidden
temporary and swapped in one step (:func:`atomic_folder`, :func:`replace_folder`); the marker that tells histojax's
temporaries from a user's files (:data:`TEMP_MARKER`), and the checks that an output folder holds nothing of the
user's before it is replaced (:func:`foreign_entries`, :func:`check_replaceable`). A full disk is one error naming
the file (:func:`as_disk_full`); a killed write leaves the previous file (or none).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import stat
import uuid
from pathlib import Path

import numpy as np

from data_tools.bundle_files.format import METADATA, READ_VERSIONS
from data_tools.errors import BundleError

__all__ = [
    "BUNDLE_EXTRAS",
    "LEFT_RUN_LOCK",
    "PARTIAL",
    "PARTIAL_ENTRY",
    "RENAME_EXCHANGE",
    "SHORT_WRITE",
    "TEMP_MARKER",
    "TEMP_MARKER_TEXT",
    "TEMP_NAME",
    "as_disk_full",
    "atomic_file",
    "atomic_folder",
    "check_replaceable",
    "foreign_entries",
    "is_our_temporary",
    "left_run_lock",
    "mark_temporary",
    "partial_foreign",
    "remove_partial",
    "remove_temporary",
    "replace_folder",
    "save_array",
    "write_json",
]


TEMP_MARKER = ".histojax-temporary"
"""The file histojax writes inside every temporary folder it makes (``.NAME.tmp-XXXXXXXX``, ``.NAME.old-XXXXXXXX``):
the cleaners of killed runs delete or rename only folders holding it (:func:`is_our_temporary`); anything else of
that name is the user's and is left alone."""


TEMP_MARKER_TEXT = b"histojax temporary folder: made by a build, removed when it ends or by the next run\n"


TEMP_NAME = re.compile(r"^\..+\.(?:tmp|old)-[0-9A-Za-z]+$")
"""Names of histojax's temporaries (``.NAME.tmp-XXXXXXXX``, ``.NAME.old-XXXXXXXX``); only the marker proves one."""


SHORT_WRITE = "requested and"  # numpy's words for a short write (``N requested and M written``): the disk is full


def mark_temporary(folder) -> Path:
    """Create the folder ``folder`` (and its parents) if absent and write :data:`TEMP_MARKER` inside it: the proof
    that histojax made it as a temporary (see :func:`is_our_temporary`). Returns ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / TEMP_MARKER).write_bytes(TEMP_MARKER_TEXT)
    return folder


def is_our_temporary(path) -> bool:
    """True when ``path`` is a real folder (not a link) holding histojax's :data:`TEMP_MARKER` (a regular file
    with its exact text): a temporary a histojax build made. A plain file, a link or a folder without the
    marker is not, whatever its name."""
    path = Path(path)
    marker = path / TEMP_MARKER
    try:
        if path.is_symlink() or not path.is_dir() or marker.is_symlink() or not marker.is_file():
            return False
        if marker.stat().st_size != len(TEMP_MARKER_TEXT):
            return False
        return marker.read_bytes() == TEMP_MARKER_TEXT
    except OSError:
        return False


def remove_temporary(path) -> bool:
    """Delete the folder ``path`` when :func:`is_our_temporary` proves histojax made it; returns whether it did."""
    if not is_our_temporary(path):
        return False
    shutil.rmtree(path, ignore_errors=True)
    return True


def as_disk_full(e: OSError) -> OSError | None:
    """A short write (numpy's ``N requested and M written``, no errno) as the ``ENOSPC`` it is ("No space left on
    device", the file name kept), else None."""
    import errno

    if e.errno is None and SHORT_WRITE in str(e):
        return OSError(errno.ENOSPC, f"No space left on device ({e})", e.filename)
    return None


@contextlib.contextmanager
def atomic_file(path):
    """Yield a temporary path for ``path``'s new content, inside a hidden marked folder beside it
    (``.NAME.tmp-XXXXXXXX/NAME``, see :func:`mark_temporary`); when the block ends the file there is fsync-ed and
    ``os.replace``-d onto ``path`` (readers never see half a file) and the folder removed. On an error the
    temporary folder is removed and ``path`` is left as it was; an ``OSError`` names ``path`` (not the temporary),
    and a short write (a full disk) says "No space left on device"."""
    path = Path(path)
    folder = path.with_name(f".{path.name}.tmp-{uuid.uuid4().hex[:8]}")
    tmp = folder / path.name
    try:
        mark_temporary(folder)
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        shutil.rmtree(folder, ignore_errors=True)
    except OSError as e:
        shutil.rmtree(folder, ignore_errors=True)
        full = as_disk_full(e)
        if full is not None:
            raise OSError(full.errno, full.strerror, str(path)) from None
        if e.filename is None or str(folder) in str(e.filename):  # name the file written, not its temporary
            raise OSError(e.errno, e.strerror or str(e), str(path)) from None
        raise
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise


def save_array(path, array: np.ndarray) -> None:
    """``np.save`` (no pickles) atomically onto ``path`` (see :func:`atomic_file`)."""
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        np.save(f, array, allow_pickle=False)


def write_json(path, data) -> None:
    """Write ``data`` as JSON (indent 1) atomically onto ``path`` (see :func:`atomic_file`)."""
    with atomic_file(path) as tmp, open(tmp, "w") as f:
        json.dump(data, f, indent=1, allow_nan=False)


BUNDLE_EXTRAS = ("features.partial",)
"""Entries a bundle may hold besides ``metadata.json`` and the files its checksums list: the chunks of an
unfinished feature grid (:mod:`data_tools.features`)."""


LEFT_RUN_LOCK = ".histojax-run.lock"
"""The lock file ``histojax train`` took in a folder it then refused (histojax 0.1.0 left it behind; now removed on
refusal): :func:`left_run_lock` tells such a leftover, which never makes a bundle or a head folder foreign."""


def left_run_lock(path) -> bool:
    """Whether ``path`` is a leftover run lock (:data:`LEFT_RUN_LOCK`): a small regular file (no link, no FIFO)
    holding only a process id, that no process holds (an ``fcntl.flock`` on it is free)."""
    import fcntl

    path = Path(path)
    try:
        st = os.lstat(path)
        if path.name != LEFT_RUN_LOCK or not stat.S_ISREG(st.st_mode) or st.st_size > 64:
            return False
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return False
    try:
        if not re.fullmatch(rb"\d*\s*", os.read(fd, 65)):
            return False
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # held by a run: not a leftover
        fcntl.flock(fd, fcntl.LOCK_UN)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


def foreign_entries(out_dir) -> list[str]:
    """The entries of the folder ``out_dir`` that histojax cannot prove it wrote as a bundle: everything when
    ``metadata.json`` is absent, not a regular file, or not a bundle's metadata (a JSON object with a known
    ``format_version`` and a ``checksums`` record); else every entry that is neither ``metadata.json``, a file
    its checksums list, :data:`BUNDLE_EXTRAS` nor a hidden ``.NAME.tmp-*`` of an interrupted atomic write.
    Empty when the folder is a bundle as histojax wrote it (or is empty)."""
    out_dir = Path(out_dir)
    entries = sorted(
        p.name for p in out_dir.iterdir() if not (p.name == TEMP_MARKER and p.is_file() and not p.is_symlink())
    )
    meta = out_dir / METADATA
    try:
        if meta.is_symlink() or not meta.is_file():
            return entries
        metadata = json.loads(meta.read_text())
    except (OSError, ValueError):
        return entries
    if (
        not isinstance(metadata, dict)
        or metadata.get("format_version") not in READ_VERSIONS
        or not isinstance(metadata.get("checksums"), dict)
    ):
        return entries
    known = {METADATA, *BUNDLE_EXTRAS, *(k for k in metadata["checksums"] if isinstance(k, str))}
    foreign = []
    for name in entries:
        p = out_dir / name
        if name.startswith(".") and ".tmp-" in name and is_our_temporary(p):
            continue
        if name == LEFT_RUN_LOCK and left_run_lock(p):  # a refused `train --out` of histojax 0.1.0 left it
            continue
        if name not in known or p.is_symlink() or (name != PARTIAL and not p.is_file()):
            foreign.append(name)
        elif name == PARTIAL:
            foreign += [f"{PARTIAL}/{n}" for n in partial_foreign(p)]
    return foreign


PARTIAL = "features.partial"
"""The folder of an unfinished feature grid inside a bundle: ``settings.json`` and ``NNNNNN.npy`` chunks."""


PARTIAL_ENTRY = re.compile(r"^(?:settings\.json|[0-9]{6}\.npy)$")


def partial_foreign(partial) -> list[str]:
    """The entries of ``BUNDLE/features.partial`` histojax did not write (anything but ``settings.json``, regular
    ``NNNNNN.npy`` chunk files and marked temporaries); everything when it is not a real folder."""
    partial = Path(partial)
    if partial.is_symlink() or not partial.is_dir():
        return [partial.name]
    foreign = []
    for p in sorted(partial.iterdir()):
        if PARTIAL_ENTRY.match(p.name) and not p.is_symlink() and p.is_file():
            continue
        if p.name.startswith(".") and ".tmp-" in p.name and is_our_temporary(p):
            continue
        foreign.append(p.name)
    return foreign


def remove_partial(partial) -> bool:
    """Delete what histojax wrote in ``BUNDLE/features.partial`` (its chunks, settings and marked temporaries),
    then the folder if that left it empty; anything else (a user's file) stays. Returns whether it is gone."""
    partial = Path(partial)
    if partial.is_symlink() or not partial.is_dir():
        return False
    foreign = set(partial_foreign(partial))
    for p in partial.iterdir():
        if p.name in foreign:
            continue
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
    try:
        partial.rmdir()
    except OSError:
        return False
    return True


def check_replaceable(out_dir) -> None:
    """Refuse to overwrite ``out_dir`` unless it is absent, an empty folder, or a bundle histojax wrote: its
    ``metadata.json`` a bundle's metadata and every other entry a file that metadata lists (see
    :func:`foreign_entries`). ``--overwrite`` must never delete files histojax did not write; a dataset folder
    (``dataset.json``) is never replaced by a bundle."""
    out_dir = Path(out_dir)
    if not (out_dir.exists() or out_dir.is_symlink()):
        return
    if out_dir.is_symlink() or not out_dir.is_dir():
        raise BundleError(
            out_dir,
            "is a file, not a bundle folder; refusing to overwrite it (remove it yourself or choose another --out)",
        )
    if not any(p.name != TEMP_MARKER for p in out_dir.iterdir()):
        return
    if (out_dir / "dataset.json").exists() or (out_dir / "dataset.json").is_symlink():
        raise BundleError(
            out_dir,
            "holds a dataset.json (a dataset folder, not a bundle); refusing to overwrite it (choose another --out)",
        )
    foreign = foreign_entries(out_dir)
    if foreign:
        what = (
            f"no readable {METADATA}"
            if METADATA in foreign or not (out_dir / METADATA).is_file()
            else f"{len(foreign)} file(s) its {METADATA} does not list, e.g. {foreign[0]!r}"
        )
        raise BundleError(
            out_dir,
            f"is a folder of other files, not a histojax bundle ({what}); refusing to "
            "overwrite it (remove them yourself or choose another --out)",
        )


RENAME_EXCHANGE = 2  # renameat2 flag (Linux >= 3.15): swap two paths atomically


def _exchange(a: Path, b: Path) -> bool:
    """Swap the folders ``a`` and ``b`` in one atomic step (Linux ``renameat2(RENAME_EXCHANGE)``); False when
    the system cannot (another OS, an old kernel or libc, a filesystem without it): nothing changed then."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd = -100
    return renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), RENAME_EXCHANGE) == 0


def replace_folder(new, out_dir) -> None:
    """Put the finished folder ``new`` (a sibling of ``out_dir``) at ``out_dir``: swapped in one atomic step
    where the system can (a reader sees the old folder or the new one, never none), else the old folder is
    renamed aside to ``.NAME.old-XXXXXXXX`` first and put back if the second rename fails. The old folder is
    marked a temporary (:func:`mark_temporary`) before it moves, so a run killed meanwhile leaves a folder the
    next run can prove is histojax's, and deleted once the new one is in place; the new ``out_dir`` keeps no
    marker (unless ``out_dir`` is itself a temporary, ``.NAME.tmp-*``). ``out_dir`` must be absent or a folder
    (not a link)."""
    new, out_dir = Path(new), Path(out_dir)

    def unmark() -> None:
        if not TEMP_NAME.match(out_dir.name):
            (out_dir / TEMP_MARKER).unlink(missing_ok=True)

    if not (out_dir.exists() or out_dir.is_symlink()):
        new.rename(out_dir)
        unmark()
        return
    if out_dir.is_symlink() or not out_dir.is_dir():
        raise BundleError(out_dir, "is a file, not a bundle folder; refusing to replace it")
    mark_temporary(out_dir)
    if _exchange(new, out_dir):
        unmark()
        shutil.rmtree(new, ignore_errors=True)  # now the old folder
        return
    old = out_dir.parent / f".{out_dir.name}.old-{uuid.uuid4().hex[:8]}"
    out_dir.rename(old)
    try:
        new.rename(out_dir)
    except BaseException:
        old.rename(out_dir)  # put the previous folder back
        unmark()
        raise
    unmark()
    shutil.rmtree(old, ignore_errors=True)


@contextlib.contextmanager
def atomic_folder(out_dir):
    """Yield a temporary sibling folder of ``out_dir`` (``.NAME.tmp-XXXXXXXX``, created and marked as histojax's,
    :func:`mark_temporary`) to fill; when the block ends it replaces ``out_dir`` (:func:`replace_folder`: an atomic
    swap where the system can, else the previous ``out_dir`` is moved aside first and put back if the rename
    fails), so a crash leaves nothing that looks like a bundle. On an error the temporary folder is removed and
    ``out_dir`` is left as it was."""
    out_dir = Path(out_dir)
    tmp = out_dir.parent / f".{out_dir.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        mark_temporary(tmp)
        yield tmp
        replace_folder(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
