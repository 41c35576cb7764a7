"""Locks and leftovers of dataset builds (shared by ``data_tools dataset`` and ``data_tools c16``).

A dataset folder may be written by several processes at once (``--jobs N``) and by several machines
sharing it (``--shard I/N``, e.g. a SLURM job array). Every bundle ``bundles/NAME`` is built while
holding ``bundles/.NAME.dataset-lock`` (``flock``, non-blocking: a bundle another process is building
is skipped, never built twice); ``dataset.json`` and the plan are written holding ``.dataset.lock``.
The kernel drops the lock of a killed process; a holder removes its lock file when done, so a
finished run leaves no lock files behind.

Leftovers of killed runs — ``.NAME.tmp-*`` / ``.NAME.old-*`` siblings of any bundle or file,
and the chunks in ``features.partial/`` of a bundle whose feature grid is finished — are removed by
:func:`clean_stale` only when nobody holds the locks of ``NAME`` (a live build's temporaries are left
alone) and only when histojax can prove it made them: every temporary folder it creates holds its marker
(:func:`data_tools.bundle_files.writes.mark_temporary`). A file or folder of such a name without the marker is the
user's: neither removed nor renamed.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import re
import shutil
from pathlib import Path

from data_tools.bundle_files.writes import TEMP_MARKER, is_our_temporary, partial_foreign, remove_partial
from data_tools.errors import HistojaxDataError

STALE = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-[0-9a-zA-Z]+$")
"""Hidden temporaries of :func:`data_tools.bundle_files.writes.atomic_folder` / ``atomic_file``."""
LOCK_FILE = re.compile(r"^\.(?P<name>.+)\.(?:dataset-)?lock$")
"""Lock files of :func:`file_lock` (``.NAME.dataset-lock``) and of the bundle builder (``.NAME.lock``)."""
BUILD_TEMP = re.compile(r"^\.(?P<name>.+)\.(?P<kind>tmp|old)-[0-9a-f]{8}$")
"""A temporary (or moved-aside) bundle folder of :func:`data_tools.bundle_files.writes.atomic_folder`."""


class LockHeld(HistojaxDataError):
    """Another live process holds the lock."""


def _acquire(path: Path, blocking: bool):
    """Open and ``flock`` ``path``; returns the fd, or None when another process holds it and not blocking.
    Loops when the previous holder removed the file between our open and our lock."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
        except BlockingIOError:
            os.close(fd)
            return None
        except OSError as e:
            if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                return fd  # no locking on this filesystem: run unlocked
            os.close(fd)
            raise
        try:
            same = os.path.samestat(os.fstat(fd), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            return fd
        os.close(fd)


def _release(path: Path, fd: int) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass
    os.close(fd)


@contextlib.contextmanager
def file_lock(path, blocking: bool = True, what: str = "this dataset"):
    """Hold an exclusive ``flock`` on ``path`` (created; removed when released). Not blocking: raises
    :class:`LockHeld` naming ``path`` when another process holds it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = _acquire(path, blocking)
    if fd is None:
        raise LockHeld(path, f"another process is writing {what} (lock held)")
    try:
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        yield path
    finally:
        _release(path, fd)


RUN_LOCK = ".dataset-run.lock"
"""``OUT/.dataset-run.lock``: every ``histojax dataset`` run into ``OUT`` holds it shared while it runs; a run that
writes another plan needs it alone (:class:`RunLock`)."""


class RunLock:
    """The lock a ``histojax dataset`` run holds on its folder for its whole run: shared by runs of one plan (shards,
    ``--jobs``, a second terminal with the same command cooperate), exclusive for the moment a run writes a new
    ``plan.json`` (a first run, ``--restart`` with other options). So a run with other options is refused while
    another holds the folder, instead of both building bundles of two settings. The kernel drops it when a run
    is killed; the last holder removes the file."""

    def __init__(self, path) -> None:
        self.path = Path(path)
        self.fd: int | None = None

    def claim(self, exclusive: bool) -> bool:
        """Take the lock (exclusive or shared), not blocking; False when another run holds it the other way."""
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, (fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH) | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                return False
            except OSError as e:
                if e.errno in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                    self.fd = fd  # no locking on this filesystem: run unlocked
                    return True
                os.close(fd)
                raise
            try:
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if same:
                self.fd = fd
                return True
            os.close(fd)  # the last holder removed this file meanwhile: take the new one

    def share(self) -> None:
        """Turn a held exclusive lock into a shared one (call it holding ``.dataset.lock``)."""
        if self.fd is not None:
            with contextlib.suppress(OSError):
                fcntl.flock(self.fd, fcntl.LOCK_SH)

    def release(self) -> None:
        """Let the lock go; the file is removed when no other run holds it."""
        if self.fd is None:
            return
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.unlink(self.path)
        except OSError:
            pass  # another run still holds it: the last one removes the file
        os.close(self.fd)
        self.fd = None


def bundle_lock_path(bundle) -> Path:
    """``bundles/.NAME.dataset-lock`` of the bundle folder ``bundles/NAME``."""
    bundle = Path(bundle)
    return bundle.parent / f".{bundle.name}.dataset-lock"


@contextlib.contextmanager
def _free(path: Path):
    """Yield True when nobody holds ``path`` (and hold it meanwhile), False when someone does."""
    fd = _acquire(path, blocking=False) if path.parent.is_dir() else None
    if fd is None and path.parent.is_dir():
        yield False
        return
    try:
        yield True
    finally:
        if fd is not None:
            _release(path, fd)


def clean_stale(folder, finished_features: bool = True, lock_folder=None) -> list[str]:
    """Remove the hidden temporaries of killed runs in ``folder`` (``.NAME.tmp-*``, ``.NAME.old-*`` of any
    NAME) whose NAME no live process is building (neither ``.NAME.dataset-lock`` nor the bundle builder's
    ``.NAME.lock`` held), and ``NAME/features.partial`` of bundles whose feature grid is finished.
    Returns the names removed (relative to ``folder``). Safe to call while other shards run.
    ``lock_folder``: where the locks of the names live (default ``folder``; e.g. ``bundles/`` for the
    slide TIFFs ``slides/.NAME.tif.tmp-*`` that ``c16`` writes holding the lock of bundle NAME); a
    temporary ``.NAME.EXT.tmp-*`` is checked against the locks of ``NAME.EXT`` and of ``NAME``."""
    folder = Path(folder)
    locks = Path(lock_folder) if lock_folder is not None else folder
    removed: list[str] = []
    if not folder.is_dir():
        return removed
    for p in sorted(folder.iterdir()):
        m = STALE.match(p.name)
        if not m or not is_our_temporary(p):  # a user's entry of that name: not ours to remove or rename
            continue
        names = dict.fromkeys([m["name"], m["name"].split(".")[0]])
        with contextlib.ExitStack() as stack:
            if not all(
                stack.enter_context(_free(locks / f".{n}.{kind}")) for n in names for kind in ("dataset-lock", "lock")
            ):
                continue
            target = folder / m["name"]
            if m["kind"] == "old" and not (target.exists() or target.is_symlink()):
                p.rename(target)  # killed between moving the previous bundle aside and the swap: put it back
                (target / TEMP_MARKER).unlink(missing_ok=True)
                removed.append(f"{p.name} (restored as {m['name']})")
                continue
            shutil.rmtree(p, ignore_errors=True)
            removed.append(p.name)
    removed += clean_lock_files(folder)
    if finished_features:
        for partial in sorted(folder.glob("*/features.partial")):
            bundle = partial.parent
            with _free(bundle_lock_path(bundle)) as free:
                if free and clean_partial_features(bundle):
                    removed.append(f"{bundle.name}/features.partial")
    return removed


def clean_lock_files(folder) -> list[str]:
    """Remove the lock files (``.NAME.lock``, ``.NAME.dataset-lock``) in ``folder`` that no live process holds
    (a killed build's): each is taken, then removed as a holder removes it. Only small files holding nothing
    or a process id (what the locks write) are looked at. Returns the names removed."""
    folder = Path(folder)
    removed: list[str] = []
    if not folder.is_dir():
        return removed
    for p in sorted(folder.iterdir()):
        if not LOCK_FILE.match(p.name) or p.is_symlink() or not p.is_file():
            continue
        try:
            if p.stat().st_size > 32 or not (p.read_bytes().strip() or b"0").isdigit():
                continue
        except OSError:
            continue
        with _free(p) as free:
            if free:
                removed.append(p.name)
    return removed


def clean_stale_builds(folder, keep=()) -> list[str]:
    """Leftovers of killed bundle builds of any name in ``folder`` (any user's folder: ``build --out``'s
    parent), removed only when they are provably histojax's and no live process holds their locks: hidden
    ``.NAME.tmp-XXXXXXXX`` / ``.NAME.old-XXXXXXXX`` folders holding histojax's marker (a ``.NAME.old-*``
    whose ``NAME`` is gone is put back as ``NAME``: the previous bundle of a swap that was killed), then
    free lock files (:func:`clean_lock_files`). ``keep``: names not to look at (the build in progress).
    Returns the names removed or restored."""
    folder = Path(folder)
    removed: list[str] = []
    if not folder.is_dir():
        return removed
    for p in sorted(folder.iterdir()):
        m = BUILD_TEMP.match(p.name)
        if not m or m["name"] in keep or not is_our_temporary(p):
            continue  # not a temporary histojax marked: not ours to judge
        with contextlib.ExitStack() as stack:
            if not all(
                stack.enter_context(_free(folder / f".{m['name']}.{kind}")) for kind in ("dataset-lock", "lock")
            ):
                continue
            target = folder / m["name"]
            if m["kind"] == "old" and not (target.exists() or target.is_symlink()):
                p.rename(target)
                (target / TEMP_MARKER).unlink(missing_ok=True)
                removed.append(f"{p.name} (restored as {m['name']})")
            else:
                shutil.rmtree(p, ignore_errors=True)
                removed.append(p.name)
    return removed + clean_lock_files(folder)


def clean_partial_features(bundle) -> bool:
    """Remove what histojax wrote in ``BUNDLE/features.partial`` (:func:`data_tools.bundle_files.writes.remove_partial`)
    when it holds no chunk or the bundle's feature grid is finished (its metadata names an encoder); a file
    there histojax did not write stays (and so does the folder). Returns whether the folder is gone. Call
    holding the bundle's lock."""
    import json

    partial = Path(bundle) / "features.partial"
    if partial.is_symlink() or not partial.is_dir():
        return False
    done = False
    try:
        done = bool((json.loads((Path(bundle) / "metadata.json").read_text()).get("features") or {}).get("encoder"))
    except (OSError, ValueError, AttributeError):
        pass
    ours = [p for p in partial.iterdir() if p.name not in set(partial_foreign(partial))]
    if done or not any(p.suffix == ".npy" for p in ours):
        return remove_partial(partial)
    return False


__all__ = [
    "LockHeld",
    "RUN_LOCK",
    "RunLock",
    "bundle_lock_path",
    "clean_lock_files",
    "clean_partial_features",
    "clean_stale",
    "clean_stale_builds",
    "file_lock",
]
