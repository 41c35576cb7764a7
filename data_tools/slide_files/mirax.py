"""Check a 3DHISTECH MIRAX slide's declared sizes before OpenSlide opens it.

OpenSlide's MIRAX reader (``src/openslide-vendor-mirax.c``) sizes its arrays from ``Slidedat.ini`` in 32-bit
integer arithmetic: ``IMAGENUMBER_X=2000000000`` (or 40000 × 40000 camera images, or ``DIGITIZER_WIDTH=1000000000``)
overflows and GLib aborts the whole process ("overflow allocating ..."), which no ``try`` can catch. This module
reads the numbers OpenSlide reads, the way GLib's key-file parser reads them, and refuses the slide against the
limits every slide reader shares (:mod:`data_tools.slide_files.limits`) in one :class:`~data_tools.errors.SlideError`
line naming the ``.mrxs`` file, before OpenSlide allocates anything. Keys that are missing or not numbers are left
to OpenSlide, which refuses them itself without crashing.

Units: px of the level concerned (a camera image is ``DIGITIZER_WIDTH`` × ``DIGITIZER_HEIGHT`` px of its zoom level).
"""

from __future__ import annotations

import configparser
import math
import os
import re
import stat
from pathlib import Path

from data_tools.errors import SlideError
from data_tools.slide_files.base import LevelInfo, check_levels
from data_tools.slide_files.limits import MAX_LEVELS, MAX_TILES, check_size

__all__ = [
    "MAX_DATA_FILES",
    "MAX_IMAGE_PIXELS",
    "SLIDEDAT_MAX_BYTES",
    "check_mirax",
    "check_mirax_files",
    "data_folder",
    "slide_files",
]

SLIDEDAT_MAX_BYTES = 1 << 20
"""OpenSlide reads at most 1 MiB of ``Slidedat.ini``."""
MAX_DATA_FILES = 100_000
"""Most ``Data*.dat`` files (``FILE_COUNT``) accepted; OpenSlide allocates a table of that many paths."""
MAX_IMAGE_PIXELS = (2**31 - 1) // 4
"""Largest camera image (``DIGITIZER_WIDTH × DIGITIZER_HEIGHT``, px): OpenSlide decodes one into a buffer of 4-byte
pixels whose size is a 32-bit integer."""
MAX_CONCAT_EXPONENT = 30
"""Largest sum of the zoom levels' ``IMAGE_CONCAT_FACTOR`` (OpenSlide computes ``1 << sum`` in an ``int``)."""

_INT = re.compile(r"\s*([+-]?\d+)\s*")


def data_folder(mrxs) -> Path:
    """The data folder of the MIRAX slide ``mrxs``: its path without the ``.mrxs`` extension (where OpenSlide
    looks for ``Slidedat.ini``, ``Index.dat`` and the ``Data*.dat`` files)."""
    text = os.fspath(mrxs)
    return Path(text[:-5] if text.lower().endswith(".mrxs") else text)


def _int(cfg, group: str, key: str) -> int | None:
    """``key`` of ``group`` as GLib's ``g_key_file_get_integer`` reads it (base 10, a 32-bit int), or None when
    absent or not such a number (OpenSlide then refuses the file itself)."""
    try:
        text = cfg.get(group, key)
    except (configparser.Error, KeyError):
        return None
    m = _INT.fullmatch(text)
    if not m:
        return None
    value = int(m.group(1))
    return value if -(2**31) <= value < 2**31 else None


def _float(cfg, group: str, key: str) -> float | None:
    """``key`` of ``group`` as a double (``g_ascii_strtod``: decimal, hex, ``inf``, ``nan``), or None."""
    try:
        text = cfg.get(group, key).strip()
    except (configparser.Error, KeyError):
        return None
    for parse in (float, float.fromhex):
        try:
            return parse(text)
        except ValueError:
            continue
    return None


def _named_files(cfg) -> list[tuple[str, str]]:
    """``(key, file name)`` of every file ``Slidedat.ini`` names for OpenSlide to open: ``INDEXFILE`` and each
    ``FILE_<n>`` of ``[DATAFILE]``."""
    named = []
    if cfg.has_option("HIERARCHICAL", "INDEXFILE"):
        named.append(("INDEXFILE", cfg.get("HIERARCHICAL", "INDEXFILE")))
    if cfg.has_section("DATAFILE"):
        named += [(k, v) for k, v in cfg.items("DATAFILE") if re.fullmatch(r"FILE_\d+", k)]
    return named


def slide_files(mrxs) -> list[Path]:
    """Every file of the MIRAX slide ``mrxs``: the ``.mrxs`` itself, then the regular files of its data folder
    (``Slidedat.ini``, ``Index.dat``, the ``Data*.dat`` files ...), sorted; [the .mrxs] when the folder is missing.
    What a cohort fingerprints, so that a changed ``Data0000.dat`` is not "already done"."""
    mrxs = Path(mrxs)
    folder = data_folder(mrxs)
    files = [mrxs]
    try:
        with os.scandir(folder) as it:
            files += sorted(Path(e.path) for e in it if e.is_file())  # a link to a file counts
    except OSError:
        pass
    return files


def check_mirax_files(path) -> None:
    """Refuse the MIRAX slide ``path`` (the ``.mrxs``) in one :class:`SlideError` line naming it and the entry when
    an entry of its data folder is a FIFO, device or socket (opening a FIFO blocks for ever), a symbolic link that
    leads outside the folder or to anything but a regular file, or when ``Slidedat.ini`` names a file
    (``INDEXFILE``, ``FILE_<n>``) that is not a plain name inside the folder. Every entry is only ``lstat``-ed:
    nothing is opened. Run before anything reads the folder (this module's ``Slidedat.ini`` read, OpenSlide's child
    process), so neither ever opens a FIFO."""
    from data_tools.bundle_files.safe_files import not_regular

    path = os.fspath(path)
    folder = data_folder(path)
    real = Path(os.path.realpath(folder))
    try:
        with os.scandir(folder) as it:
            entries = []
            for e in it:
                entries.append(e)
                if len(entries) > MAX_DATA_FILES + 16:
                    raise SlideError(
                        path,
                        f"its data folder {folder.name}/ holds over {MAX_DATA_FILES + 16:,} entries: not a MIRAX slide",
                    )
    except OSError as exc:
        raise SlideError(path, f"cannot list its data folder {folder.name}/: {exc.strerror or exc}") from None
    for e in sorted(entries, key=lambda e: e.name):
        where = f"{folder.name}/{e.name}"
        if not where.isprintable():  # a newline or another control character in a name: the refusal stays one line
            where = repr(where)
        try:
            st = e.stat(follow_symlinks=False)
        except OSError:
            continue  # gone since listed: OpenSlide says so if it needs it
        what = not_regular(st)
        if what in (None, "a folder"):
            continue  # a subfolder is not read by OpenSlide
        if what == "a symbolic link":
            target = Path(os.path.realpath(e.path))
            if target.parent != real and real not in target.parents:
                raise SlideError(
                    path, f"{where} in its data folder is a symbolic link leading outside the folder: refused"
                )
            try:
                st = os.stat(target)
            except OSError:
                continue  # a broken link: OpenSlide refuses the file it names
            what = not_regular(st)
            if what is None or what == "a folder":
                continue
            what = f"a symbolic link to {what}"
        raise SlideError(
            path,
            f"{where} in its data folder is {what}, not a regular file: refused before opening (a FIFO "
            "would block the open)",
        )
    ini = folder / "Slidedat.ini"
    cfg = _read(ini) if ini.is_file() else None
    for key, name in _named_files(cfg) if cfg is not None else ():
        name = name.strip()
        if not name or name in (".", "..") or "/" in name or "\\" in name or "\0" in name:
            raise SlideError(
                path, f"its Slidedat.ini names {key}={name!r}: not a file name inside its data folder, refused"
            )


def _read(ini: Path):
    """``Slidedat.ini`` parsed as a GLib key file, or None when it is not one (OpenSlide refuses it then)."""
    try:  # never blocks: O_NONBLOCK, and only a regular file is read
        fd = os.open(ini, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                return None
            data = f.read(SLIDEDAT_MAX_BYTES + 1)
    except OSError:
        return None  # OpenSlide says why
    if len(data) > SLIDEDAT_MAX_BYTES:
        return None  # OpenSlide refuses a Slidedat.ini over 1 MiB
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return None
    # GLib strips each line's leading whitespace (a line is a key, a group or a comment, never the continuation
    # configparser makes of an indented line): "  [HIERARCHICAL]" then "INDEXFILE=../x" is a group and its key to
    # OpenSlide, and must be so here, or a name or a size checked below hides in another key's value
    text = "\n".join(line.lstrip(" \t\r\v\f") for line in text.split("\n"))
    cfg = configparser.RawConfigParser(
        strict=False, interpolation=None, delimiters=("=",), comment_prefixes=("#",), inline_comment_prefixes=None
    )
    cfg.optionxform = str  # GLib keys are case-sensitive
    try:
        cfg.read_string(text)
    except configparser.Error:
        return None
    return cfg


def check_mirax(path) -> None:
    """Refuse the MIRAX slide ``path`` (the ``.mrxs`` file) in one :class:`SlideError` line naming it when its
    data folder or ``Slidedat.ini`` is missing, an entry of the folder is a FIFO, device or outside link
    (:func:`check_mirax_files`), or ``Slidedat.ini`` declares sizes beyond the shared limits:
    camera images (``IMAGENUMBER_X × IMAGENUMBER_Y``) over ``MAX_TILES``, zoom levels (``HIER_0_COUNT``) over
    ``MAX_LEVELS``, ``FILE_COUNT`` over :data:`MAX_DATA_FILES`, a camera image (``DIGITIZER_WIDTH`` ×
    ``DIGITIZER_HEIGHT``) with a side over ``MAX_SIDE`` or over :data:`MAX_IMAGE_PIXELS`, overlaps that are not
    finite or not smaller than an image, concat factors summing past :data:`MAX_CONCAT_EXPONENT`, and a pyramid
    (level 0 = the camera images laid edge to edge, less their overlaps) outside ``MAX_SIDE`` / ``MAX_PIXELS`` or
    with a level under 1 px. Returns None when nothing is wrong (or what is wrong is left to OpenSlide)."""
    path = os.fspath(path)
    folder = data_folder(path)
    if not folder.is_dir():
        raise SlideError(
            path,
            f"its data folder {folder.name}/ is missing (a MIRAX slide is the .mrxs file and the "
            "folder of the same name beside it, holding Slidedat.ini, Index.dat and the Data*.dat "
            "files: copy both)",
        )
    check_mirax_files(path)  # no FIFO, device or outside link in the folder: nothing below blocks in open
    ini = folder / "Slidedat.ini"
    if not ini.is_file():
        raise SlideError(path, f"its data folder {folder.name}/ has no Slidedat.ini: not a whole MIRAX slide")
    cfg = _read(ini)
    if cfg is None:
        return

    def refuse(problem: str):
        raise SlideError(path, f"its Slidedat.ini declares {problem}: corrupt, or not a slide histojax reads")

    nx, ny = _int(cfg, "GENERAL", "IMAGENUMBER_X"), _int(cfg, "GENERAL", "IMAGENUMBER_Y")
    div = _int(cfg, "GENERAL", "CameraImageDivisionsPerSide")
    div = 1 if div is None and not cfg.has_option("GENERAL", "CameraImageDivisionsPerSide") else div
    if nx is None or ny is None or div is None or nx <= 0 or ny <= 0 or div <= 0:
        return
    if nx * ny > MAX_TILES:
        refuse(
            f"IMAGENUMBER_X × IMAGENUMBER_Y = {nx:,} × {ny:,} = {nx * ny:,} camera images, over the limit of "
            f"{MAX_TILES:,}"
        )
    files = _int(cfg, "DATAFILE", "FILE_COUNT")
    if files is not None and files > MAX_DATA_FILES:
        refuse(f"FILE_COUNT={files:,} data files, over the limit of {MAX_DATA_FILES:,}")
    if cfg.get("HIERARCHICAL", "HIER_0_NAME", fallback=None) != "Slide zoom level":
        return
    zoom = _int(cfg, "HIERARCHICAL", "HIER_0_COUNT")
    if zoom is None or zoom <= 0:
        return
    if zoom > MAX_LEVELS:
        refuse(f"HIER_0_COUNT={zoom:,} zoom levels, over the limit of {MAX_LEVELS}")
    sections = []
    for k in range(zoom):
        name = cfg.get("HIERARCHICAL", f"HIER_0_VAL_{k}_SECTION", fallback=None)
        if name is None or not cfg.has_section(name):
            return
        w, h = _int(cfg, name, "DIGITIZER_WIDTH"), _int(cfg, name, "DIGITIZER_HEIGHT")
        concat = _int(cfg, name, "IMAGE_CONCAT_FACTOR")
        ox, oy = _float(cfg, name, "OVERLAP_X"), _float(cfg, name, "OVERLAP_Y")
        if None in (w, h, concat, ox, oy) or w <= 0 or h <= 0 or concat < 0 or (k and concat == 0):
            return
        check_size(path, w, h, f"a camera image of zoom level {k} (DIGITIZER_WIDTH × DIGITIZER_HEIGHT in Slidedat.ini)")
        if w * h > MAX_IMAGE_PIXELS:
            refuse(
                f"camera images of {w:,} × {h:,} px at zoom level {k}, over {MAX_IMAGE_PIXELS:,} px (OpenSlide "
                "decodes one into a buffer of 32-bit size)"
            )
        if not (math.isfinite(ox) and math.isfinite(oy) and abs(ox) < w and abs(oy) < h):
            refuse(
                f"an overlap of {ox:g} × {oy:g} px at zoom level {k} for camera images of {w:,} × {h:,} px "
                "(an overlap must be finite and smaller than the image)"
            )
        sections.append((w, h, concat, ox, oy))
    total = sum(s[2] for s in sections)
    if total > MAX_CONCAT_EXPONENT:
        refuse(f"IMAGE_CONCAT_FACTOR values summing to {total} over the zoom levels, over {MAX_CONCAT_EXPONENT}")
    w0, h0, _, ox, oy = sections[0]

    def base(n: int, size: int, overlap: float) -> int:  # OpenSlide's sum: images edge to edge, less overlaps
        overlapped = n // div - (1 if (n - 1) % div == div - 1 else 0)
        return int(n * size - overlapped * overlap)

    base_w, base_h = base(nx, w0, ox), base(ny, h0, oy)
    levels, exponent = [], 0
    for k, (w, h, concat, _, _) in enumerate(sections):
        exponent += concat
        levels.append(
            LevelInfo(
                width=base_w >> exponent,
                height=base_h >> exponent,
                downsample=float(2 ** (exponent - sections[0][2])),
                tile_size=None,
                compression="openslide",
            )
        )
    try:
        check_levels(path, levels)
    except SlideError as e:
        raise SlideError(path, f"its Slidedat.ini declares a pyramid histojax refuses: {e.problem}") from None
