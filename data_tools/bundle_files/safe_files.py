"""Safe reads of a user's files: the one regular-file guard every reader shares (:func:`not_regular`,
:func:`open_regular`, :func:`own_file`: no symbolic link, FIFO, device or folder read in place of a bundle's own
file; a file that changes between the check and the open is refused), and :func:`stable_read`, which reads a
bundle again when a concurrent rebuild swapped it mid-read.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from data_tools.bundle_files.format import METADATA
from data_tools.errors import BundleError

__all__ = ["ChangedFileError", "not_regular", "open_regular", "own_file", "safe_name", "stable_read"]


def safe_name(name, where) -> str:
    """``name`` if it is a plain file name inside the bundle folder (no folder part, not ``.``/``..``),
    else ``BundleError``: metadata may only point at the bundle's own files."""
    if (
        not isinstance(name, str)
        or not name
        or name in (".", "..")
        or "/" in name
        or "\\" in name
        or "\0" in name
        or Path(name).name != name
    ):
        raise BundleError(where, f"file entry {name!r} is not a file name inside the bundle; rebuild the bundle")
    return name


def not_regular(st: os.stat_result) -> str | None:
    """None when ``st`` (an ``os.lstat`` result) is a regular file; else what the entry is instead (``"a symbolic
    link"``, ``"a FIFO"``, ``"a folder"``, ``"a device"``, ``"a socket"``): the one regular-file guard every reader
    of a user's files shares (bundles here, slide heads in :mod:`histojax.reading.heads.files`). A FIFO would block
    ``open``; a link may point anywhere."""

    mode = st.st_mode
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISLNK(mode):
        return "a symbolic link"
    if stat.S_ISFIFO(mode):
        return "a FIFO"
    if stat.S_ISDIR(mode):
        return "a folder"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "a device"
    return "a socket" if stat.S_ISSOCK(mode) else "not a regular file"


class ChangedFileError(OSError):
    """The file opened is not the regular file :func:`not_regular` checked (swapped in between)."""


def open_regular(path, st: os.stat_result):
    """``path`` opened for binary reading (a file object), after :func:`not_regular` passed on its ``lstat``
    result ``st``: opened with ``O_NOFOLLOW | O_NONBLOCK`` (a link put there since fails with ``ELOOP``; a FIFO
    never blocks) and ``fstat``-ed again. ``ChangedFileError`` when what was opened is not a regular file or not
    the same file as ``st`` (device, inode); ``OSError`` when it cannot be opened."""

    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    f = os.fdopen(fd, "rb")
    now = os.fstat(f.fileno())
    if not stat.S_ISREG(now.st_mode) or (now.st_dev, now.st_ino) != (st.st_dev, st.st_ino):
        f.close()
        raise ChangedFileError(f"{path}: not the regular file checked (it changed while it was opened)")
    return f


def own_file(bundle, name: str, what: str = "file") -> Path:
    """``BUNDLE/NAME`` after checking that the entry is the bundle's own regular file: a plain name
    (:func:`safe_name`), present, not a symbolic link, a FIFO, a device or a folder (``os.lstat``,
    :func:`not_regular`), whose resolved path lies in the bundle folder. Else a ``BundleError`` naming the bundle
    and the entry: a bundle never reads a file outside itself (``ln -s /etc/passwd BUNDLE/tissue.npy`` is
    refused)."""
    bundle = Path(bundle)
    file = bundle / safe_name(name, bundle / METADATA)
    try:
        st = os.lstat(file)
    except FileNotFoundError:
        raise BundleError(bundle, f"missing {what} {name}; rebuild the bundle") from None
    except OSError as e:
        raise BundleError(bundle, f"entry {name!r} cannot be read ({e.strerror or e}); rebuild the bundle") from None
    kind = not_regular(st)
    if kind == "a symbolic link":
        try:
            target = os.readlink(file)
        except OSError:
            target = "?"
        raise BundleError(
            bundle,
            f"entry {name!r} is a symbolic link (to {target}), not the bundle's own file; "
            "refusing to read it (rebuild the bundle)",
        )
    if kind is not None:
        raise BundleError(bundle, f"entry {name!r} is not a regular file; refusing to read it (rebuild the bundle)")
    if os.path.realpath(file.parent) != os.path.realpath(bundle):
        raise BundleError(bundle, f"entry {name!r} resolves outside the bundle; refusing to read it")
    return file


def _identity(path):
    """``(device, inode, ctime)`` of the folder at ``path`` (a rename sets its ctime), ``None`` when there is none."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino, st.st_ctime_ns


def _rebuilding(path: Path) -> bool:
    """True while a build of ``path`` is under way: its temporary folder, moved-aside old folder or build lock
    lies beside it (see :func:`atomic_folder` and :func:`data_tools.bundle.build_lock`)."""
    import glob as _glob

    stem = str(path.parent / f".{_glob.escape(path.name)}.")
    return bool(_glob.glob(stem + "tmp-*") or _glob.glob(stem + "old-*") or os.path.exists(stem + "lock"))


def stable_read(path, read, attempts: int = 12):
    """``read()`` of the bundle at ``path``, repeated when the folder was swapped while it ran (a rebuild with
    ``--overwrite`` renames a new folder into place, see :func:`atomic_folder`): a verified read is all of the
    old bundle or all of the new one, never a mix, and a swap is never reported as corruption. A read is
    repeated when the folder's identity (inode, ctime) changed, or when it failed while a rebuild was under
    way (a ``BundleError``, or an ``OSError`` such as a file that vanished mid-swap); an error with no rebuild in
    sight is raised at once, and after ``attempts`` tries (10 s of waits in all,
    doubling from 5 ms: a reader outlasts a busy machine's run of back-to-back rebuilds)."""
    import time

    path = Path(path)
    for attempt in range(attempts):
        last = attempt == attempts - 1
        before = _identity(path)
        try:
            result = read()
        except (BundleError, OSError):  # OSError: a file vanished between the rename aside and the new folder's
            if last or (_identity(path) == before and not _rebuilding(path)):
                raise
            time.sleep(0.005 * 2**attempt)
            continue
        if last or _identity(path) == before:
            return result
        time.sleep(0.005 * 2**attempt)
    raise AssertionError("unreachable")
