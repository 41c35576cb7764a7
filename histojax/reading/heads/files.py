"""Reading and writing slide-head folders safely: one guarded path for every head kind.

A head folder holds ``config.json`` (the head's kind, format and structure: a JSON object) and its parameters
(``params.npz``: named float arrays), and maybe files its writer listed in ``config.json``'s ``"files"`` (a
learning curve, a README). Head folders come from other people (a published head, a colleague's run), so
reading one follows the bundle rules (:func:`data_tools.bundle_files.safe_files.own_file`):

* **Regular files only.** Each file is ``lstat``-ed before it is opened: a symbolic link, a FIFO, a device
  or a folder is refused (a FIFO would block ``open``; a link may point anywhere). It is then opened with
  ``O_NOFOLLOW | O_NONBLOCK`` and ``fstat``-ed again (the file swapped in between is refused too).
* **Sizes bounded before reading**: ``config.json`` at most :data:`MAX_CONFIG_BYTES` (1 MiB), parameters at
  most :data:`MAX_PARAMS_BYTES` (64 MiB) on disk, and each array at most that once decompressed.
* **JSON**: UTF-8, nesting at most :data:`MAX_JSON_DEPTH` deep (checked on the text before parsing: no
  ``RecursionError``), no ``NaN`` / ``Infinity``, no repeated keys; fields read with strict types
  (:func:`field`: a bool is ``true``/``false``, not ``"false"``; an int is a JSON integer; a float is finite).
* **Arrays**: ``allow_pickle=False``; every member's ``.npy`` header (shape, dtype) is checked against the
  shapes the config implies *before* its data is read: exactly the expected names (no missing, no unused
  arrays), float dtypes only (no object, complex or structured arrays), the member's size matching its header
  (no truncated or padded data), finite values.

Any problem raises :class:`HeadFileError` (a ``ValueError``): one line naming the file and the problem.

:func:`save_folder` writes a head atomically: into a marked temporary folder beside the target
(``.NAME.tmp-XXXXXXXX``, holding :data:`TEMP_MARKER`), ``config.json`` last (it records every file the head
wrote), then renamed into place in one step (:func:`data_tools.bundle_files.writes.replace_folder`). It never
replaces a folder that holds anything else: user files, a head of another kind, a link or a plain file.
"""

from __future__ import annotations

import io
import json
import math
import os
import shutil
import tempfile
import uuid
import zipfile
from pathlib import Path

import numpy as np

from data_tools.bundle_files.safe_files import ChangedFileError, not_regular, open_regular
from data_tools.bundle_files.writes import left_run_lock, replace_folder

CONFIG = "config.json"
PARAMS = "params.npz"
MAX_CONFIG_BYTES = 1 << 20
"""``config.json`` larger than this (1 MiB) is refused unread."""
MAX_PARAMS_BYTES = 64 << 20
"""``params.npz`` larger than this (64 MiB) on disk, or any array in it larger than this decompressed, is refused
(a head of a 4,096-d encoder with 1,024 hidden units holds 16 MiB of float32)."""
MAX_JSON_DEPTH = 32
"""Deepest nesting of JSON arrays / objects read (a head config is 2-3 deep)."""
TEMP_MARKER = ".histojax-temporary"
"""The file written inside a temporary head folder: proof that histojax made it (only such folders are removed)."""
FLOAT_DTYPES = ("float16", "float32", "float64")


class HeadFileError(ValueError):
    """A head folder's file cannot be read or written as a head's: ``"FILE: problem"``, one line."""

    def __init__(self, path, problem: str):
        self.path, self.problem = os.fspath(path), problem
        super().__init__(f"{self.path}: {problem}")


MAX_ARRAY_VALUE = 1e6
"""The largest magnitude of any entry of a head's ``params.npz`` (weights, biases, means, calibration,
``prior_logit``), as the logit heads bound ``a``, ``b`` and ``prior_logit``: a fitted head's are a few units."""


def check_magnitudes(arrays: dict, path, min_sd: float) -> None:
    """Refuse (``HeadFileError`` naming ``path``, one line) the arrays of a head's ``params.npz`` (name -> array)
    with an entry beyond :data:`MAX_ARRAY_VALUE` in magnitude, or a standardisation ``sd`` below ``min_sd`` (what
    the head's fit adds to every standard deviation, or less): finite but absurd values that would score every
    slide −inf or NaN (``x / 1e-40``, ``3e38 · s``)."""
    if "sd" in arrays and np.any(arrays["sd"] < min_sd):
        raise HeadFileError(
            path,
            f"array sd holds values below {min_sd:g} (a feature's standard deviation, at "
            f"least {min_sd:g} in a fitted head)",
        )
    for name, arr in arrays.items():
        top = float(np.max(np.abs(arr))) if np.size(arr) else 0.0
        if top > MAX_ARRAY_VALUE:
            raise HeadFileError(
                path,
                f"array {name} holds values of magnitude up to {top:.3g}, beyond "
                f"{MAX_ARRAY_VALUE:g} (a fitted head's are a few units); refusing it",
            )


def check_finite_logits(head, logits, what: str = "slide logits"):
    """``logits`` (any shape) as a NumPy array (its dtype kept) when every entry is finite; else
    ``HeadFileError`` naming the parameters file of ``head`` (its ``source`` folder's ``params.npz``, or the head's
    name when it was not loaded from a folder), one line: a head whose values overflow scores every slide alike
    (an AUC of 0.5 or 1.0 that means nothing). What every host-side scorer of a head's logits calls before it uses
    them."""
    values = np.asarray(logits)
    if values.size and not np.all(np.isfinite(values)):
        bad = int(np.size(values) - np.count_nonzero(np.isfinite(values)))
        source = getattr(head, "source", None)
        where = Path(source) / PARAMS if source else f"{PARAMS} of the head {getattr(head, 'name', head)!r}"
        raise HeadFileError(
            where,
            f"scores {bad} of {values.size} {what} non-finite (inf or NaN): its parameters "
            "are out of a fitted head's range; refit the head (learned_head_fit)",
        )
    return values


# ----------------------------------------------------------------------------- guarded reads
def read_regular(path, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of ``path`` after checking it is a regular file (not a link, FIFO, device or folder: the bundles'
    guard, :func:`data_tools.bundle_files.safe_files.not_regular` and :func:`~data_tools.bundle_files.safe_files.open_regular`) of at
    most ``max_bytes`` bytes; ``HeadFileError`` naming it otherwise (or when it is missing)."""
    path = Path(path)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        raise HeadFileError(path, f"missing (a slide head folder holds {CONFIG} and its parameters)") from None
    except OSError as e:
        raise HeadFileError(path, f"cannot be read ({e.strerror or e})") from None
    kind = not_regular(st)
    if kind == "a symbolic link":
        raise HeadFileError(path, f"is a symbolic link, not the head's own {what}; refusing to read it")
    if kind is not None:
        raise HeadFileError(
            path, f"is not a regular file (a FIFO, device or folder); refusing to read it as the head's {what}"
        )
    if st.st_size > max_bytes:
        raise HeadFileError(
            path, f"{st.st_size:,} bytes, more than the {max_bytes:,} a head's {what} may have; refusing to read it"
        )
    try:
        f = open_regular(path, st)
    except ChangedFileError:
        raise HeadFileError(
            path, "changed while it was opened (not the regular file checked); refusing to read it"
        ) from None
    except OSError as e:
        raise HeadFileError(path, f"cannot be opened ({e.strerror or e})") from None
    with f:
        now = os.fstat(f.fileno())
        data = f.read(min(now.st_size, max_bytes) + 1)  # its size, not the cap: a small file costs no more
    if len(data) > min(now.st_size, max_bytes):
        raise HeadFileError(path, "grew while it was read; refusing it")
    return data


def json_depth(text: str) -> int:
    """The deepest nesting of ``[`` / ``{`` in the JSON ``text`` (brackets inside strings not counted)."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


def _no_constant(name):
    raise ValueError(f"{name} is not a number a head config may hold")


def _unique(pairs):
    out = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"key {k!r} appears twice")
        out[k] = v
    return out


def read_config(path, max_bytes: int = MAX_CONFIG_BYTES, max_depth: int = MAX_JSON_DEPTH, what: str = "config") -> dict:
    """The JSON object in ``path`` (a head's ``config.json``; ``what="parameters"``: its ``params.json``, named so in
    the messages), read through :func:`read_regular`: UTF-8, nested at most ``max_depth`` deep, no NaN / Infinity,
    no repeated key. ``HeadFileError`` naming the file otherwise."""
    data = read_regular(path, max_bytes, what)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as e:
        raise HeadFileError(path, f"not UTF-8 text ({e.reason} at byte {e.start})") from None
    depth = json_depth(text)
    if depth > max_depth:
        raise HeadFileError(path, f"JSON nested {depth} deep, more than the {max_depth} a head {what} may be")
    try:
        cfg = json.loads(text, parse_constant=_no_constant, object_pairs_hook=_unique)
    except (ValueError, RecursionError) as e:  # JSONDecodeError is a ValueError; so is an over-long integer
        detail = " ".join(str(e).split())[:160].replace("a head config may hold", f"a head's {what} may hold")
        raise HeadFileError(path, f"not valid JSON ({detail})") from None
    if not isinstance(cfg, dict):
        raise HeadFileError(path, f"holds a JSON {type(cfg).__name__}, not an object (a head {what})")
    return cfg


_MISSING = object()


def field(cfg: dict, key: str, kind: type, where, default=_MISSING, lo=None, hi=None):
    """``cfg[key]`` checked to be of ``kind`` (``bool``, ``int``, ``float``, ``str``, ``list`` or ``dict``), strictly:
    a bool must be ``true`` / ``false`` (not ``"false"`` or 0), an int a JSON integer (not ``true`` or 2.0), a float
    a finite number; numbers within ``[lo, hi]`` when given. ``default`` when absent (else refused).
    ``HeadFileError`` naming ``where`` (the config file) and the key."""
    if key not in cfg:
        if default is _MISSING:
            raise HeadFileError(where, f"lacks {key!r}")
        return default
    v = cfg[key]
    if kind is bool:
        ok = type(v) is bool
    elif kind is int:
        ok = type(v) is int
    elif kind is float:
        ok = type(v) in (int, float) and math.isfinite(v)
        v = float(v) if ok else v
    else:
        ok = isinstance(v, kind)
    if not ok:
        what = (
            "a finite number"
            if kind is float
            else "an int"
            if kind is int
            else f"a {getattr(kind, '__name__', None) or ' or '.join(k.__name__ for k in kind)}"
        )
        raise HeadFileError(where, f"{key!r} is {json.dumps(v)[:60]}, not {what}")
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise HeadFileError(where, f"{key!r} is {v}, outside [{lo}, {hi}]")
    return v


def read_arrays(path, shapes: dict, max_bytes: int = MAX_PARAMS_BYTES) -> dict:
    """The float arrays of the ``.npz`` at ``path`` as float32, exactly the names of ``shapes`` (name -> shape
    tuple) with those shapes (an entry ``None``: any size along that axis, the caller checks it). Every member's ``.npy`` header is checked before its data is read: a missing or
    unused array, a non-float dtype (object, complex, structured), another shape, a member whose size disagrees
    with its header (truncated), more than ``max_bytes`` decompressed, non-finite values, an empty or truncated
    archive: ``HeadFileError`` naming the file, one line. ``allow_pickle`` is never on."""
    path = Path(path)
    data = read_regular(path, max_bytes, "parameters")
    if not data:
        raise HeadFileError(path, "empty file (not a .npz archive of the head's parameters)")
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, ValueError, EOFError) as e:
        raise HeadFileError(path, f"not a complete .npz archive (truncated or another format: {e})") from None
    with zf:
        infos = zf.infolist()
        names = [i.filename[:-4] if i.filename.endswith(".npy") else i.filename for i in infos]
        if len(set(names)) != len(names) or any(not i.filename.endswith(".npy") for i in infos):
            raise HeadFileError(path, "holds repeated or non-.npy members; not a head's parameters")
        missing = sorted(set(shapes) - set(names))
        unused = sorted(set(names) - set(shapes))
        if missing:
            raise HeadFileError(path, f"lacks the arrays {', '.join(missing)}")
        if unused:
            raise HeadFileError(path, f"holds arrays this head does not use ({', '.join(unused[:5])}); refusing it")
        out = {}
        for info, name in zip(infos, names):
            if info.file_size > max_bytes:
                raise HeadFileError(
                    path, f"array {name} is {info.file_size:,} bytes decompressed, more than {max_bytes:,}; refusing it"
                )
            try:
                with zf.open(info) as f:
                    version = np.lib.format.read_magic(f)
                    read_header = (
                        np.lib.format.read_array_header_1_0
                        if version == (1, 0)
                        else np.lib.format.read_array_header_2_0
                    )
                    shape, fortran, dtype = read_header(f)
                    header = f.tell()
                    if (
                        dtype.hasobject
                        or dtype.fields is not None
                        or dtype.subdtype is not None
                        or dtype.name not in FLOAT_DTYPES
                    ):
                        raise HeadFileError(
                            path,
                            f"array {name} has dtype {dtype}; a head's parameters are floats "
                            f"({', '.join(FLOAT_DTYPES)})",
                        )
                    want = tuple(shapes[name])
                    if len(shape) != len(want) or any(w is not None and n != w for n, w in zip(shape, want)):
                        raise HeadFileError(
                            path,
                            f"array {name} has shape {tuple(shape)}, the config implies "
                            f"{tuple('any' if w is None else w for w in want)}",
                        )
                    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
                    if info.file_size != header + nbytes:
                        raise HeadFileError(
                            path,
                            f"array {name} holds {info.file_size - header:,} data bytes, its "
                            f"header says {nbytes:,} (truncated or padded)",
                        )
                    raw = f.read(nbytes)
                if len(raw) != nbytes:
                    raise HeadFileError(path, f"array {name} is truncated")
                arr = np.frombuffer(raw, dtype=dtype)
                arr = arr.reshape(shape, order="F" if fortran else "C").astype(np.float32)
            except HeadFileError:
                raise
            except (ValueError, OSError, EOFError, zipfile.BadZipFile, NotImplementedError) as e:
                problem = " ".join(str(e).split())[:160] or type(e).__name__
                raise HeadFileError(path, f"array {name} unreadable ({problem})") from None
            if not np.all(np.isfinite(arr)):
                raise HeadFileError(path, f"array {name} holds non-finite values")
            out[name] = arr
    return out


# ----------------------------------------------------------------------------- atomic writes
def check_writable(folder) -> None:
    """Refuse (``HeadFileError`` naming ``folder``, one line) a head folder this process cannot write, before any
    fit: a probe file is made and removed where a save writes (``folder`` when it is a folder, and the nearest
    existing folder above it, where the atomic save makes its temporary). Nothing is left behind; a read-only
    file system refuses root too, which ``os.access`` would not say."""
    folder = Path(folder)
    above = folder.parent
    while not os.path.lexists(above) and above != above.parent:
        above = above.parent
    for place in ([folder] if folder.is_dir() and not folder.is_symlink() else []) + [above]:
        try:
            fd, probe = tempfile.mkstemp(prefix=".histojax-write-check-", dir=place)
        except OSError as e:
            where = "" if place == folder else f" (its folder {place} is not writable)"
            raise HeadFileError(
                folder,
                f"cannot be written: {e.strerror or e}{where}; choose another --out "
                "(checked before fitting: nothing was fitted)",
            ) from None
        os.close(fd)
        os.unlink(probe)


def check_replaceable(folder, kind: str) -> None:
    """Refuse (``HeadFileError``) to replace ``folder`` unless it is absent, empty, or a head folder of ``kind``
    holding only the files its ``config.json`` lists (``"files"``) besides ``config.json`` itself; and unless it
    can be written (:func:`check_writable`)."""
    folder = Path(folder)
    check_writable(folder)
    if not (folder.exists() or folder.is_symlink()):
        return
    if folder.is_symlink() or not folder.is_dir():
        raise HeadFileError(folder, "is a link or a file, not a head folder; refusing to replace it")
    entries = sorted(p.name for p in folder.iterdir() if not left_run_lock(p))  # a leftover lock: replaced too
    if not entries:
        return
    if CONFIG not in entries:
        raise HeadFileError(
            folder,
            f"holds files that are not a slide head's (no {CONFIG}: e.g. {entries[0]!r}); "
            "refusing to overwrite it (choose another folder)",
        )
    try:
        cfg = read_config(folder / CONFIG)
    except HeadFileError as e:
        raise HeadFileError(
            folder, f"holds a {CONFIG} that is not a slide head's ({e.problem}); refusing to overwrite it"
        ) from None
    other = cfg.get("kind")
    if other != kind:
        raise HeadFileError(
            folder,
            f"holds a head of kind {other!r}; refusing to overwrite it with a {kind!r} head (choose another folder)",
        )
    listed = cfg.get("files")
    listed = set(listed) if isinstance(listed, list) and all(isinstance(n, str) for n in listed) else {PARAMS}
    foreign = [n for n in entries if n != CONFIG and n not in listed]
    if foreign:
        raise HeadFileError(
            folder,
            f"holds files the head there did not write (e.g. {foreign[0]!r}); refusing to "
            "overwrite it (remove them yourself or choose another folder)",
        )
    links = [n for n in entries if (folder / n).is_symlink() or not (folder / n).is_file()]
    if links:
        raise HeadFileError(folder, f"entry {links[0]!r} is not a regular file; refusing to overwrite the folder")


def save_folder(folder, config: dict, arrays: dict, extras: dict | None = None) -> Path:
    """Write a head folder atomically: ``params.npz`` (``arrays``: name -> float array, saved float32),
    ``extras`` (file name -> bytes, e.g. a learning curve PNG) and ``config.json`` (``config`` plus ``"files"``,
    the names of every file written besides itself), into a marked temporary folder beside ``folder`` that is
    then renamed onto it in one step. Refused (``HeadFileError``, nothing written) when ``folder`` holds
    anything but a head of the same ``config["kind"]`` and the files it listed. Returns ``folder``."""
    folder = Path(folder)
    kind = config.get("kind")
    if not isinstance(kind, str):
        raise ValueError("a head config needs a string 'kind'")
    extras = dict(extras or {})
    for name in extras:
        if (
            not isinstance(name, str)
            or name in (CONFIG, PARAMS, TEMP_MARKER)
            or Path(name).name != name
            or name.startswith(".")
        ):
            raise ValueError(f"extra file name {name!r} is not a plain file name a head folder may hold")
    check_replaceable(folder, kind)
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = folder.parent / f".{folder.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        tmp.mkdir()
        (tmp / TEMP_MARKER).write_bytes(b"histojax temporary head folder: removed when the write ends\n")
        with open(tmp / PARAMS, "wb") as f:
            np.savez(f, **{k: np.asarray(v, np.float32) for k, v in arrays.items()})
        for name, data in extras.items():
            (tmp / name).write_bytes(data)
        cfg = {**config, "files": [PARAMS, *sorted(extras)]}
        (tmp / CONFIG).write_text(json_text(cfg))
        for name in os.listdir(tmp):
            if name != TEMP_MARKER:
                with open(tmp / name, "rb+") as f:
                    os.fsync(f.fileno())
        (tmp / TEMP_MARKER).unlink()
        replace_folder(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def json_value(v):
    """``json.dumps``'s ``default`` for every head file: a NumPy scalar as its Python number, an array as a list,
    anything else as its text."""
    if isinstance(v, (np.floating, np.integer)):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return str(v)


def json_text(obj) -> str:
    """``obj`` as a head file's JSON text (indented, strict: no NaN / Infinity, :func:`json_value` for NumPy
    values), ending in a newline."""
    return json.dumps(obj, indent=1, default=json_value, allow_nan=False) + "\n"


INPUT = "finest-level feature grid (H, W, D) and read mask (H, W) bool of read tissue views"
"""What every head reads (``config.json``'s ``input``)."""


class SavedHead:
    """The files every head class shares: :meth:`config` (``config.json``: ``kind``, ``format``, the class's
    :meth:`structure`, ``encoder``, ``name``, ``input``, ``output`` and the fit's ``info``, in that order) and
    :meth:`write` (the parameters file then ``config.json``, each through a temporary file renamed onto it). A
    head class sets ``kind``, ``FORMAT`` and maybe ``OUTPUT``, and has ``structure()``, ``encoder``, ``name`` and
    ``info`` (JSON text of an object)."""

    OUTPUT = "slide tumour logit (sigmoid: probability)"

    def structure(self) -> dict:
        """The head's own structure entries of ``config.json`` (its sizes and options)."""
        raise NotImplementedError

    def config(self) -> dict:
        """The structure as saved in ``config.json``."""
        return {
            "kind": self.kind,
            "format": self.FORMAT,
            **self.structure(),
            "encoder": self.encoder,
            "name": self.name,
            "input": INPUT,
            "output": self.OUTPUT,
            **json.loads(self.info),
        }

    def write(self, folder, params_name: str, params: bytes) -> Path:
        """Write ``folder/params_name`` (``params``) and ``folder/config.json`` (:meth:`config`); returns the
        folder."""
        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        for name, data in ((params_name, params), (CONFIG, json_text(self.config()).encode())):
            tmp = folder / f".{name}.tmp"
            tmp.write_bytes(data)
            tmp.replace(folder / name)
        return folder
