"""Run folders: which folder a training run may write, and one writer per folder.

A run folder holds only what histojax wrote there (:data:`RUN_ENTRIES`): ``log.csv``, ``log.json``,
``curve.png``, ``params.msgpack``, ``config.json``, ``checkpoint/``, TensorBoard events, ``process-N/``,
``eval/``, ``previous-N/`` (a run moved aside by ``--restart``) and the lock file. :func:`claim_run` decides,
before anything is written:

* an absent or empty folder (or one holding only ``previous-N/``): the run starts there;
* the folder of an *unfinished* run (``checkpoint/`` but no ``params.msgpack``) of the same config: the run
  *continues* from its last checkpoint (``checkpoint/runner.msgpack``), so the same command rerun after a kill
  (a scheduler's requeue) loses nothing; a run killed before its first checkpoint starts again;
* the folder of a *finished* run of the same config (an explicit ``--out``): nothing to do;
* anything else (a finished run or an unfinished run of another config, a user's file, a slide head folder) is
  refused in one line naming the folder, what it holds and the first entries its config differs in, suggesting
  ``--restart`` or ``--overwrite``;
* ``--restart``: the run there (finished or not, of any config) is moved aside whole into the folder's next
  ``previous-N/`` (never deleted) and the run starts again;
* ``--overwrite`` replaces a finished run or another config's run: only entries histojax wrote (a user's file
  there is still refused), the previous run's final files staying until the new run's are written as a whole.
  An unfinished run of the same config still continues (a job script with ``--overwrite`` rerun by a scheduler
  must not lose its run); ``--restart`` starts it again;
* the default folder ``runs/<algo>-<env>`` is never overwritten: when it holds something but an unfinished run
  of this config, the run goes to the first free ``runs/<algo>-<env>-2``, ``-3``, ... (as Stable-Baselines3
  numbers its log folders ``PPO_1``, ``PPO_2``).

One writer per run folder: :func:`claim_run` takes an exclusive ``fcntl.flock`` on ``RUN/.histojax-run.lock``
and holds it until :func:`release` (or the process's end: the operating system drops the lock of a killed
process, so a killed run never leaves its folder locked). A second ``train --out RUN`` or ``--resume RUN`` while
one holds it is refused in one line.

A refused command leaves the folder as it found it: :func:`claim_run` checks the folder before it creates it or
the lock, :func:`release` removes the lock file, and removes the folder too when this process made it and it is
still empty (a run refused after its claim, e.g. for a mistyped ``--fold``).
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import re
import shutil
import stat
from pathlib import Path

from data_tools.bundle_files.safe_files import ChangedFileError, not_regular, open_regular
from data_tools.bundle_files.writes import is_our_temporary
from data_tools.errors import HistojaxDataError

LOCK = ".histojax-run.lock"
"""The lock file inside a run folder (held with ``fcntl.flock`` while a run writes there)."""
FINAL = ("log.csv", "log.json", "curve.png", "params.msgpack", "config.json")
"""A finished run's files (written as a whole at its end)."""
RUN_ENTRIES = re.compile(
    r"^(log\.csv|log\.json|curve\.png|params\.msgpack|config\.json|checkpoint|eval|"
    r"eval-all-folds|head_reward\.json|curve-seeds\.png|curve-seeds\.csv|slides_seen\.json|"
    r"process-\d+|previous-\d+|events\.out\.tfevents\..+|\.histojax-run\.lock|\..+\.tmp-[0-9a-f]{8})$"
)
"""Names histojax writes in a run folder (temporaries of an atomic write included): a trainer's files,
``eval/`` and ``eval-all-folds/`` (``histojax evaluate RUN`` and ``--all-folds``), ``head_reward.json`` and
``curve-seeds.*`` (``baselines.reading.train_readers``), ``slides_seen.json`` (the slides a dataset run trained
on: :func:`baselines.reading.provenance.write_run_record`), ``previous-N/`` (a run ``--restart`` moved aside, kept
whole and never looked into)."""
PREVIOUS = re.compile(r"^previous-(\d+)$")
"""A run folder's ``previous-N/``: the run that ``--restart`` moved aside (N = 1, 2, ...)."""
STATE = (
    "checkpoint",
    "eval",
    "eval-all-folds",
    "head_reward.json",
    "curve-seeds.png",
    "curve-seeds.csv",
    "slides_seen.json",
)
"""What ``--overwrite`` removes before the new run (the old run's state and what was derived from it;
``slides_seen.json`` too: a new run on no dataset writes none, and the old one would name slides it never saw);
its final files (:data:`FINAL`) stay until the new run's are written."""
MAX_NUMBERED = 1000
"""The most numbered default folders (``runs/<algo>-<env>-N``) tried."""

_HELD: dict[
    str, tuple[int, Path, Path | None]
] = {}  # run folder (resolved) -> (lock fd, folder, outermost folder made)


class RunFolderError(HistojaxDataError):
    """A run folder a training run may not write (file named, one line)."""


MAX_CONFIG_BYTES = 16 << 20
"""A run's ``config.json`` larger than this (16 MiB; a trainer writes about 1 KB) is not read."""


def read_own(path, what: str, max_bytes: int | None = None) -> bytes:
    """The bytes of a run folder's own file ``path`` (``what`` it is, for the message): a regular file, not a
    symbolic link (it may point anywhere), a FIFO (``open`` would block forever), a device or a folder, of at most
    ``max_bytes`` bytes when given. ``RunFolderError`` naming it otherwise; ``OSError`` (e.g. missing) as ``open``
    raises it."""
    path = Path(path)
    st = os.lstat(path)
    kind = not_regular(st)
    if kind is not None:
        raise RunFolderError(
            path,
            f"is {kind}, not the run's own {what}; refusing to read it (restore the file "
            "histojax wrote, or train again)",
        )
    if max_bytes is not None and st.st_size > max_bytes:
        raise RunFolderError(
            path, f"{st.st_size:,} bytes, more than a run's {what} holds ({max_bytes:,}); refusing to read it"
        )
    try:
        f = open_regular(path, st)
    except ChangedFileError:
        raise RunFolderError(path, f"changed while it was opened; refusing to read it as the run's {what}") from None
    with f:
        return f.read() if max_bytes is None else f.read(max_bytes + 1)


def _is_run_config(path: Path) -> bool:
    """Whether ``path`` is a run's ``config.json`` as a trainer writes it: a regular file (never a link or a FIFO,
    which would block the read) holding a JSON object that names its ``env_id``."""
    try:
        config = json.loads(read_own(path, "config", MAX_CONFIG_BYTES))
    except (OSError, ValueError, RecursionError, HistojaxDataError):  # not a regular file, too large, not JSON
        return False  # (or nested deeper than the parser recurses): not a run's config
    return isinstance(config, dict) and isinstance(config.get("env_id"), str)


INSIDE = {
    "checkpoint": re.compile(r"^(runner\.msgpack|checkpoint\.json|config\.json|\..+\.tmp-[0-9a-f]{8})$"),
    "eval": re.compile(
        r"^(eval\.json|eval\.csv|trajectory\.gif|trajectory_.+\.png|reading_.+\.png|slide\d+|"
        r"fold\d+|\..+\.tmp-[0-9a-f]{8})$"
    ),
    "eval-all-folds": re.compile(
        r"^(eval\.json|eval\.csv|trajectory\.gif|trajectory_.+\.png|reading_.+\.png|"
        r"slide\d+|fold\d+|\..+\.tmp-[0-9a-f]{8})$"
    ),
    "process": re.compile(r"^(params\.msgpack|config\.json|\..+\.tmp-[0-9a-f]{8})$"),
}
"""Names histojax writes inside a run folder's ``checkpoint/``, ``eval/`` (and its ``slideN/``, ``foldN/``) and
``eval-all-folds/`` and ``process-N/``: what ``--overwrite`` may remove there."""


def _foreign_inside(folder: Path, names: re.Pattern, prefix: str) -> list[str]:
    """The entries below ``folder`` (a run's ``checkpoint/``, ``eval/`` or ``process-N/``) that histojax does not
    write there, as ``prefix/NAME``: a name it never writes, a link, a FIFO or other non-file, a folder where it
    writes none."""
    foreign = []
    for name in sorted(os.listdir(folder)):
        path, where = folder / name, f"{prefix}/{name}"
        if path.is_symlink() or not names.match(name):
            foreign.append(where)
        elif path.is_dir():
            if re.match(r"^(slide|fold)\d+$", name):
                foreign += _foreign_inside(path, names, where)
            elif not (".tmp-" in name and is_our_temporary(path)):  # an interrupted atomic write's marked folder
                foreign.append(where)
        elif not path.is_file():
            foreign.append(where)
    return foreign


def foreign_entries(out: Path) -> list[str]:
    """The entries of ``out`` that histojax does not write in a run folder (a user's files), sorted: names a run
    never holds, a symbolic link of any name (a run writes none: ``checkpoint`` linked elsewhere would write
    there), and a ``config.json`` / ``checkpoint/config.json`` that is not a run's config (a user's notes,
    a slide head's config)."""
    foreign = [n for n in os.listdir(out) if not RUN_ENTRIES.match(n) or (n != LOCK and (out / n).is_symlink())]
    for name in ("config.json", "checkpoint/config.json"):
        if (out / name).exists() and not _is_run_config(out / name):
            foreign.append(name)
    if (out / "checkpoint").exists() and not (out / "checkpoint").is_dir():
        foreign.append("checkpoint")
    foreign += [n for n in os.listdir(out) if PREVIOUS.match(n) and not (out / n).is_dir()]  # a run moved aside
    return sorted(set(foreign))


def _read_config(path: Path) -> dict | None:
    """The JSON object in the run's own file ``path`` (``config.json``); None when it is absent or unreadable."""
    try:
        config = json.loads(read_own(path, "config", MAX_CONFIG_BYTES))
    except (OSError, ValueError, RecursionError, HistojaxDataError):
        return None
    return config if isinstance(config, dict) else None


def _checkpoint_config(out: Path) -> dict | None:
    return _read_config(out / "checkpoint" / "config.json")


def _shown(value) -> str:
    return json.dumps(value, sort_keys=True, default=str)  # json-not-written (a message)


def _brief(value, most: int = 80) -> str:
    text = _shown(value)
    return text if len(text) <= most else text[: most - 3] + "..."


def _nested_difference(key: str, saved_value, value) -> str:
    """How the saved entry ``key`` differs from the command's: for two objects (``env_kwargs``) the first inner
    entry that differs, named ``key.inner`` (an 80-character cut of the whole objects would hide it), e.g.
    ``env_kwargs.read_budget is 0.2, not 0.3``; else both values."""
    if isinstance(saved_value, dict) and isinstance(value, dict):
        if key in PINNED:
            saved_value = {k: v for k, v in saved_value.items() if k not in PINNED[key] or k in value}
        for k in sorted(set(saved_value) | set(value), key=str):
            if k not in saved_value:
                return f"{key} has no {k} (this command's: {_brief(value[k])})"
            if k not in value:
                return f"{key}.{k} is {_brief(saved_value[k])} (this command has none)"
            if _shown(saved_value[k]) != _shown(value[k]):
                return _nested_difference(f"{key}.{k}", saved_value[k], value[k])
    return f"{key} is {_brief(saved_value)}, not {_brief(value)}"


def difference(saved: dict | None, config: dict, most: int = 2) -> str:
    """How the saved run config ``saved`` differs from the command's ``config`` (the first ``most`` entries of
    ``config`` that differ, in its order), for a refusal: e.g. ``whose lr is 0.0003, not 0.001``; ``saved`` None:
    its config cannot be read."""
    if saved is None:
        return "whose config.json cannot be read"
    saved = {**ADDED, **saved}
    parts = [
        _nested_difference(k, saved[k], v) if k in saved else f"config has no {k} (this command's: {_brief(v)})"
        for k, v in config.items()
        if k not in saved or not _entry_same(k, saved[k], v)
    ]
    if not parts:
        return "of this config"
    more = f" (and {len(parts) - most} more)" if len(parts) > most else ""
    return "whose " + "; ".join(parts[:most]) + more


COMPLETED = {"obs_norm": "dataset"}
"""Command values a trainer replaces with what it computed (``obs_norm="dataset"``: the training slides'
normaliser, :func:`baselines.ppo.resolve_obs_norm`): a saved config holding the computed value is of that command."""
PINNED = {"env_kwargs": ("glimpse_grid",)}
"""Entries a trainer adds inside a config's entry (:func:`baselines.common.env.pin_env_shapes`): a saved config
holding them where the command has none is of that command."""


ADDED = {"minibatch_by": "sample"}
"""Entries trainers recorded only from a later version, with the value runs had before: a saved config without the
entry is of a command giving that value (a run started before the entry existed still continues)."""


def _entry_same(key: str, saved_value, value) -> bool:
    """Whether the saved config's entry ``key`` (``saved_value``) is what the command's ``value`` makes."""
    if key in COMPLETED and value == COMPLETED[key] and not isinstance(saved_value, str):
        return True
    if key in PINNED and isinstance(saved_value, dict) and isinstance(value, dict):
        saved_value = {k: v for k, v in saved_value.items() if k not in PINNED[key] or k in value}
    return _shown(saved_value) == _shown(value)


def _same(saved: dict, config: dict) -> bool:
    """Whether the checkpoint's full config ``saved`` is a run of ``config`` (the command's entries, which the
    trainer completes with its own): every entry of ``config`` equal in ``saved`` (:func:`_entry_same`)."""
    saved = {**ADDED, **saved}  # entries recorded only later, at the value runs had before
    return all(k in saved and _entry_same(k, saved[k], v) for k, v in config.items())


def lock(out: Path) -> None:
    """Take the exclusive lock of the run folder ``out`` (created if absent) for the rest of this process (or until
    :func:`release`); ``RunFolderError`` naming the folder when another process holds it. Taking it twice in one
    process is a no-op. A refusal leaves no lock file and no folder it created."""
    out = Path(out)
    key = os.path.realpath(out)
    if key in _HELD:
        return
    made = _first_missing(out)
    for _ in range(20):  # a holder that releases removes the file: lock the file the name holds now
        try:
            out.mkdir(parents=True, exist_ok=True)
            fd = os.open(
                out / LOCK,
                os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | os.O_CLOEXEC | getattr(os, "O_NONBLOCK", 0),
                0o644,
            )  # a FIFO there never blocks the open
        except OSError as e:
            _remove_made(out, made)
            if e.errno == errno.ELOOP:
                raise RunFolderError(
                    out / LOCK, "is a symbolic link, not the run folder's lock file; remove it or choose another --out"
                ) from None
            raise RunFolderError(out, f"cannot be written ({e.strerror or e}); choose another --out") from None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            os.close(fd)
            raise RunFolderError(
                out / LOCK,
                "is not a regular file (a FIFO, device or socket), not the run folder's "
                "lock file; remove it or choose another --out",
            )
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
            finally:
                os.close(fd)
            raise RunFolderError(
                out,
                f"another training run (process {holder}) is writing this run folder (it holds "
                f"{LOCK}); wait for it to end, or choose another --out",
            ) from None
        try:
            now = os.lstat(out / LOCK)
        except FileNotFoundError:
            now = None
        if now is not None and (now.st_dev, now.st_ino) == (st.st_dev, st.st_ino):
            break
        os.close(fd)  # the file was removed by the holder's release after our open: take the new one
    else:
        raise RunFolderError(out, f"its {LOCK} kept changing while it was taken; choose another --out")
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    _HELD[key] = (fd, out, made)


def _first_missing(out: Path) -> Path | None:
    """The outermost folder of ``out`` (``out`` itself or one of its parents) that does not exist yet: what
    ``mkdir(parents=True)`` would create first; None when ``out`` exists."""
    missing = None
    for folder in (out, *out.parents):
        if os.path.lexists(folder):
            break
        missing = folder
    return missing


def _remove_made(out: Path, made: Path | None) -> None:
    """Remove the folder ``out`` and its parents up to ``made`` (the outermost this process created) while they
    are empty: a refusal leaves no folder behind that the command created."""
    if made is None:
        return
    for folder in (out, *out.parents):
        try:
            folder.rmdir()
        except OSError:
            return  # not empty (the run wrote something) or already gone
        if folder == made:
            return


def release(out: Path) -> None:
    """Drop this process's lock of the run folder ``out`` (the end of a run, or a refusal): the lock file is
    removed, and so is the folder when this process made it and it is now empty. A process that ends drops the
    lock too (its file then stays until the next claim)."""
    held = _HELD.pop(os.path.realpath(Path(out)), None)
    if held is None:
        return
    fd, folder, made = held
    try:
        st, now = os.fstat(fd), os.lstat(folder / LOCK)
        if (now.st_dev, now.st_ino) == (st.st_dev, st.st_ino):
            os.unlink(folder / LOCK)  # removed while held: a process waiting on it re-opens the name (lock())
    except OSError:
        pass  # already gone
    finally:
        os.close(fd)
    _remove_made(folder, made)


def _names(out: Path) -> list[str]:
    """The entries of ``out`` that are its run (all but the lock file and the runs moved aside, ``previous-N/``)."""
    return [n for n in os.listdir(out) if n != LOCK and not (PREVIOUS.match(n) and (out / n).is_dir())]


def _state(out: Path, config: dict) -> str:
    """``"empty"`` (nothing but the lock and ``previous-N/``), ``"unfinished-same"`` (a checkpoint of ``config``,
    no final params), ``"finished-same"`` (final params, ``config.json`` of ``config``), ``"finished"``,
    ``"unfinished-other"`` or ``"foreign"`` (entries histojax does not write)."""
    if not _names(out):
        return "empty"
    if foreign_entries(out):
        return "foreign"
    if (out / "params.msgpack").exists():
        saved = _read_config(out / "config.json")
        return "finished-same" if saved is not None and _same(saved, config) else "finished"
    saved = _checkpoint_config(out)
    if saved is not None and _same(saved, config):
        return "unfinished-same"
    return "unfinished-other"


def _check(out: Path, config: dict, overwrite: bool, restart: bool = False) -> str:
    """The state of the existing folder ``out`` (:func:`_state`) when a run of ``config`` may be written there
    (``restart``: whatever run is there, moved aside; ``overwrite``: a finished run or another config's replaced);
    ``RunFolderError`` naming it otherwise. Writes nothing."""
    state = _state(out, config)
    if state == "empty":
        return state
    foreign = foreign_entries(out)
    if foreign:
        raise RunFolderError(
            out,
            f"holds files histojax did not write (e.g. {foreign[0]!r}); refusing to train "
            "into it (choose another --out; --overwrite and --restart touch only a run's own files)",
        )
    if restart or state == "unfinished-same" or (state == "finished-same" and not overwrite):
        return state  # moved aside whole (nothing removed), continued, or nothing to do
    if not overwrite:
        if state == "finished":
            what = f"a finished run (params.msgpack) {difference(_read_config(out / 'config.json'), config)}"
            keep = "choose another --out"
        else:
            what = f"an unfinished run of another config, {difference(_checkpoint_config(out), config)}"
            keep = f"continue it with --resume {out} (its own config), choose another --out"
        raise RunFolderError(
            out,
            f"holds {what}; refusing to overwrite it: {keep}, start again with --restart (moves it to "
            f"{out}/previous-N), or replace it with --overwrite",
        )
    inside = []  # a user's file inside the old run's folders: never removed (refused before anything is)
    for name in sorted(os.listdir(out)):
        kind = "process" if re.match(r"^process-\d+$", name) else name
        if kind in INSIDE and (out / name).is_dir():
            inside += _foreign_inside(out / name, INSIDE[kind], name)
    if inside:
        raise RunFolderError(
            out,
            f"holds files histojax did not write (e.g. {inside[0]!r}) in the old run's "
            "folders, which --overwrite would remove; move them out first, use --restart (moves the run aside "
            "whole), or choose another --out",
        )
    return state


def _progress(out: Path) -> str:
    """``update k/N`` of the unfinished run in ``out`` (its ``checkpoint/checkpoint.json``), or ``its last
    checkpoint`` when that summary cannot be read."""
    try:
        saved = json.loads(read_own(out / "checkpoint" / "checkpoint.json", "checkpoint summary", MAX_CONFIG_BYTES))
        update, total = saved["update"], saved["num_updates"]
    except (OSError, ValueError, RecursionError, TypeError, KeyError, HistojaxDataError):
        return "its last checkpoint"
    if type(update) is int and type(total) is int and 0 <= update <= total:  # not Infinity, NaN, true, "3", -5
        return f"update {update}/{total}"
    return "its last checkpoint"


def move_aside(out: Path) -> Path:
    """Move the run in ``out`` (every entry but the lock and the earlier ``previous-N/``) into a new
    ``out/previous-N/`` (N one more than the largest there) by renames, its ``checkpoint/`` first: nothing is
    deleted, and a move killed midway leaves no half of a run that would be continued. Returns the folder."""
    out = Path(out)
    taken = [int(m.group(1)) for n in os.listdir(out) if (m := PREVIOUS.match(n))]
    dest = out / f"previous-{max(taken, default=0) + 1}"
    dest.mkdir()
    for name in sorted(_names(out), key=lambda n: (n != "checkpoint", n)):
        os.rename(out / name, dest / name)
    return dest


def claim(out, config: dict, overwrite: bool = False, default: bool = False, restart: bool = False) -> Path:
    """The folder a run of ``config`` writes, locked and checked: :func:`claim_run`'s folder."""
    return claim_run(out, config, overwrite=overwrite, default=default, restart=restart)[0]


def claim_run(
    out, config: dict, overwrite: bool = False, default: bool = False, restart: bool = False
) -> tuple[Path, str]:
    """The folder a run of ``config`` writes, locked (:func:`lock`) and checked (module doc), and what the run
    does there: ``"new"`` (an empty folder), ``"resume"`` (continue the unfinished run of this config from
    ``checkpoint/``), ``"again"`` (a run of this config killed before its first checkpoint: start it again),
    ``"done"`` (a finished run of this config: nothing to train), ``"restarted"`` (the run there moved aside,
    :func:`move_aside`) or ``"replaced"`` (``overwrite``). What it decided is printed in one line (but for
    ``"new"``). ``default``: ``out`` is the default ``runs/<algo>-<env>``, so a used one moves the run to the next
    free numbered folder. ``RunFolderError`` naming the folder, one line, when it may not be written."""
    out = Path(out)
    if default and not overwrite:
        for n in range(1, MAX_NUMBERED + 1):
            candidate = out if n == 1 else out.with_name(f"{out.name}-{n}")
            if (
                candidate.is_dir()
                and not candidate.is_symlink()
                and _state(candidate, config) not in ("empty", "unfinished-same")
            ):
                continue
            if candidate.exists() and not candidate.is_dir():
                continue
            try:
                return claim_run(candidate, config, restart=restart)
            except RunFolderError:
                continue  # held by another run: the next number
        raise RunFolderError(out, f"{out}-2 ... {out}-{MAX_NUMBERED} are all used; choose a folder with --out")
    if out.is_symlink() or (out.exists() and not out.is_dir()):
        raise RunFolderError(out, "is a file or a link, not a run folder; choose another --out")
    if out.is_dir():
        _check(out, config, overwrite, restart)  # refused before the lock is taken: the folder stays as it was
    lock(out)
    try:
        state = _check(out, config, overwrite, restart)  # again under the lock: another process may have written
    except RunFolderError:
        release(out)
        raise
    if state == "empty":
        return out, "new"
    if restart:
        dest = move_aside(out)
        print(f"{out}: moved the run there aside to {dest} (--restart); starting again", flush=True)
        return out, "restarted"
    if state == "unfinished-same":
        if os.path.lexists(out / "checkpoint" / "runner.msgpack"):
            print(
                f"{out} holds an unfinished run of this config at {_progress(out)}: continuing it "
                "(--restart starts again)",
                flush=True,
            )
            return out, "resume"
        print(f"{out} holds a run of this config killed before its first checkpoint: starting it again", flush=True)
        return out, "again"
    if state == "finished-same" and not overwrite:
        print(
            f"{out} holds a finished run of this config (params.msgpack): nothing to train (--restart trains it again)",
            flush=True,
        )
        return out, "done"
    for name in STATE:  # the old run's state: replaced; its final files stay until the new ones
        path = out / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.is_file() and not path.is_symlink():
            path.unlink()
    for name in os.listdir(out):
        if name.startswith(("events.out.tfevents.", "process-")):
            path = out / name
            shutil.rmtree(path) if path.is_dir() and not path.is_symlink() else path.unlink()
    return out, "replaced"
