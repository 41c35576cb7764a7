"""Read whole-slide images through OpenSlide 4 (the optional extra ``openslide``), behind the interface of
:class:`data_tools.slide_files.base.SlideReader` (``levels``, ``mpp``, ``read_level``, ``read_region``).

This module's one job: give the formats the native readers do not read (3DHISTECH MIRAX ``.mrxs``, Leica
``.scn``, Ventana ``.bif``, Hamamatsu ``.vms`` / ``.vmu``, Sakura ``.svslide``, Philips TIFF) the same
interface as a TIFF, so that ``info`` / ``build`` (dense and tiled) / ``dataset`` read them; any slide
OpenSlide reads can be sent here with ``--reader openslide``. ``openslide-python`` (LGPL-2.1) and
``openslide-bin`` (the OpenSlide 4 library as a wheel): ``pip install 'histojax[openslide]'``.

What OpenSlide reports is what histojax uses: the levels (``level_dimensions``, ``level_downsamples``),
µm per level-0 px (``openslide.mpp-x``, else ``openslide.mpp-y``) and the associated images (label, macro,
thumbnail ...: names and sizes in :attr:`OpenSlideReader.associated`). Regions outside the slide, and
transparent pixels OpenSlide returns where a scanner stored nothing, are white (255), as the native readers
give them.

A file is never given to OpenSlide in this process first: a MIRAX slide's ``Slidedat.ini`` is checked against the
limits every reader shares (:mod:`data_tools.slide_files.mirax`, :mod:`data_tools.slide_files.limits`), then every slide is opened in a
child process (:func:`_probe`), so that a file that makes OpenSlide abort (GLib's "overflow allocating") or crash
stops only that child and is refused here in one line; the levels OpenSlide reports are checked against the same
limits.

Units as in :mod:`data_tools.slide_files.tiff`: pixels of the level read, ``downsample`` in level-0 px per level px,
``mpp`` in µm per level-0 px. Every problem with the file raises :class:`data_tools.errors.SlideError`
naming the path, in one line.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import signal
import stat
import subprocess
import sys

import numpy as np

from data_tools.errors import SlideError
from data_tools.slide_files.base import LevelInfo, SlideReader, check_levels
from data_tools.slide_files.dicom import _dicom_files, is_dicom
from data_tools.slide_files.limits import MAX_LEVELS, MAX_PIXELS, MAX_SIDE
from data_tools.slide_files.mirax import check_mirax

__all__ = ["INSTALL_HINT", "OPENSLIDE_EXTENSIONS", "OpenSlideReader", "openslide_available", "openslide_module"]

INSTALL_HINT = "reading it needs the optional extra: pip install 'histojax[openslide]' (OpenSlide 4)"
OPENSLIDE_EXTENSIONS = {
    ".mrxs": "3DHISTECH MIRAX",
    ".scn": "Leica SCN",
    ".bif": "Ventana BIF",
    ".vms": "Hamamatsu VMS",
    ".vmu": "Hamamatsu VMU",
    ".svslide": "Sakura SVSlide",
}
"""Slide files read through OpenSlide (the native readers do not read them): extension → format name."""


def openslide_module():
    """The ``openslide`` module (openslide-python with the OpenSlide 4 library), or ``None`` when the
    optional extra is not installed (or its library cannot be loaded)."""
    try:
        import openslide  # optional extra: histojax[openslide]
    except (ImportError, OSError):
        return None
    return openslide


def openslide_available() -> bool:
    """True when the optional extra ``openslide`` is installed and its library loads."""
    return openslide_module() is not None


def _one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text and text[0] else type(exc).__name__


class OpenSlideReader(SlideReader):
    """An open slide read by OpenSlide.

    Attributes as :class:`data_tools.slide_files.base.SlideReader`; ``format`` is ``"openslide-"`` + OpenSlide's
    vendor (``"openslide-mirax"``, ``"openslide-aperio"``, ``"openslide-generic-tiff"`` ...); ``levels``
    are OpenSlide's, finest first, with its tile size where it reports one and ``compression``
    ``"openslide"`` (OpenSlide does not say); ``associated`` maps each associated image's name (``"label"``,
    ``"macro"``, ``"thumbnail"`` ...) to its ``(width, height)`` in px.
    """

    def __init__(self, path: str | os.PathLike):  # noqa: D107 (opens the file)
        self.path = os.fspath(path)
        self._handle = None  # the open openslide.OpenSlide (SlideReader's name for the open handle)
        self.format = "openslide"
        self.associated: dict[str, tuple[int, int]] = {}
        openslide = openslide_module()
        if openslide is None:
            raise SlideError(self.path, INSTALL_HINT)
        try:
            mode = os.stat(self.path).st_mode
        except FileNotFoundError:
            raise SlideError(self.path, "file not found") from None
        except OSError as exc:
            raise SlideError(self.path, f"cannot read file: {exc.strerror or exc}") from None
        if stat.S_ISDIR(mode) and is_dicom(self.path):  # a DICOM WSI folder: OpenSlide opens the series by one file
            self.path = _dicom_files(self.path)[0]
            mode = os.stat(self.path).st_mode
        if not stat.S_ISREG(mode):
            what = "a folder" if stat.S_ISDIR(mode) else "not a regular file (a FIFO, socket or device)"
            raise SlideError(
                self.path, f"is {what}: OpenSlide opens one slide file (for MIRAX the .mrxs, its data folder beside it)"
            )
        if self.path.lower().endswith(".mrxs"):  # its Slidedat.ini's sizes, before OpenSlide sizes arrays by them
            check_mirax(self.path)
        try:
            vendor = openslide.OpenSlide.detect_format(self.path)
            if vendor is None:
                raise SlideError(
                    self.path,
                    "format not recognised by OpenSlide (not a slide it reads, or corrupt); "
                    "OpenSlide reads Aperio SVS, MIRAX, Hamamatsu, Leica SCN, Philips TIFF, "
                    "Sakura, Ventana, DICOM WSI and tiled TIFF",
                )
            _probe(self.path)  # in a child process first: a file that makes OpenSlide abort takes only the child
            self._handle = openslide.OpenSlide(self.path)
            self.format = f"openslide-{vendor}"
            props = self._handle.properties
            self.levels = _level_infos(self._handle, props)
            check_levels(self.path, self.levels)
            self.mpp = _mpp(props)
            self.associated = {
                name: tuple(int(v) for v in img.size) for name, img in self._handle.associated_images.items()
            }
            last = self.levels[-1]  # one pixel of the coarsest level: catches a broken file at open
            self._decode_window(len(self.levels) - 1, last.width - 1, last.height - 1, last.width, last.height)
        except SlideError:
            self.close()
            raise
        except Exception as exc:  # OpenSlideError, OpenSlideUnsupportedFormatError, OS errors: never escape raw
            self.close()
            raise SlideError(self.path, f"format not recognised or file corrupt (OpenSlide: {_one_line(exc)})") from exc

    def __repr__(self) -> str:
        return f"OpenSlideReader({self.path!r}, format={self.format!r}, levels={len(self.levels)})"

    def _decode_window(self, level: int, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """RGB pixels of the in-bounds window [y0:y1, x0:x1] of ``level``: (y1-y0, x1-x0, 3) uint8.

        OpenSlide takes the top-left corner in level-0 px and paints the level from ``corner / downsample``:
        where that is not a whole level pixel (a level whose downsample is not a whole number, as most SVS
        pyramids have: 4.0003 ...) it interpolates between pixels. So the window is read from a corner
        :func:`_aligned_start` finds a little above and left of it, whose level position is whole to
        1/1000 px, and cropped: the level's stored pixels, as the native readers return them."""
        ds = self.levels[level].downsample
        (sx, gx), (sy, gy) = _aligned_start(x0, ds), _aligned_start(y0, ds)
        try:
            region = self._handle.read_region((sx, sy), level, (x1 - gx, y1 - gy))
            rgba = np.asarray(region, dtype=np.uint8)
        except Exception as exc:  # OpenSlideError (a corrupt tile), OS errors
            raise SlideError(
                self.path, f"cannot decode level {level} (OpenSlide: {_one_line(exc)}); file truncated or corrupt"
            ) from exc
        if rgba.shape != (y1 - gy, x1 - gx, 4):
            raise SlideError(self.path, f"level {level} decoded to {rgba.shape}, not RGBA of {x1 - gx}×{y1 - gy} px")
        return _on_white(rgba[y0 - gy :, x0 - gx :])


PROBE_TIMEOUT_S = 60
"""Seconds the child process that first opens a slide with OpenSlide (and reads one pixel) may take before it is
stopped and the slide refused, saying so: opening a slide reads its index, not its pixels (a few seconds on a
large slide); a file that makes OpenSlide wait longer is refused rather than holding a cohort up."""
PROBE_MEMORY_BYTES = 8 << 30
"""Address space of that child (bytes): a file that makes OpenSlide allocate more is refused, not swapped in."""

_PROBE_CODE = r"""
import json, sys
sys.path.pop(0)  # not the working folder's modules
try:
    import resource
    resource.setrlimit(resource.RLIMIT_AS, (int(sys.argv[2]), int(sys.argv[2])))
except Exception:
    pass
import openslide
path, side, pixels, levels = sys.argv[1], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
try:
    s = openslide.OpenSlide(path)
except Exception as exc:
    print(json.dumps({"error": type(exc).__name__}))
    sys.exit(0)
dims = [tuple(int(v) for v in d) for d in s.level_dimensions]
sane = 0 < len(dims) <= levels and dims[0][0] * dims[0][1] <= pixels and all(0 < w <= side and 0 < h <= side
                                                                          for w, h in dims)
if sane:  # one pixel of the coarsest level, as the reader does at open
    w, h = dims[-1]
    ds = s.level_downsamples[-1]
    try:
        s.read_region((int((w - 1) * ds), int((h - 1) * ds)), len(dims) - 1, (1, 1))
    except Exception:
        pass
print(json.dumps({"levels": dims}))
"""
_probed: dict[tuple, bool] = {}


def _identity(path: str) -> tuple:
    """What the probe of ``path`` depends on: its real path and the size and mtime of it and of the files of a
    MIRAX data folder beside it."""
    from data_tools.slide_files.mirax import data_folder

    files = [path]
    folder = data_folder(path)
    if path.lower().endswith(".mrxs") and folder.is_dir():
        files += sorted(str(f) for f in folder.iterdir())[:10_000]
    out = [os.path.realpath(path)]
    for f in files:
        try:
            st = os.stat(f)
            out.append((f, st.st_ino, st.st_size, st.st_mtime_ns))
            if f.endswith("Slidedat.ini") and stat.S_ISREG(st.st_mode) and st.st_size <= 1 << 20:  # its bytes too
                with open(f, "rb") as fh:
                    out.append(hashlib.sha256(fh.read()).hexdigest())
        except OSError:
            out.append((f, None))
    return tuple(out)


def _probe(path: str) -> None:
    """Open ``path`` with OpenSlide in a child process (and read one pixel of its coarsest level when its sizes are
    within the shared limits) before this process does: a file that makes OpenSlide abort (GLib's "overflow
    allocating"), crash or run out of its :data:`PROBE_MEMORY_BYTES` kills only the child, and is refused here in one
    :class:`SlideError` line naming it. A file OpenSlide merely refuses is left to the open that follows (which says
    why); a child that cannot start is passed over. Successes are remembered per file identity (size, mtime)."""
    key = _identity(path)
    if key in _probed:
        return
    argv = [
        sys.executable,
        "-c",
        _PROBE_CODE,
        path,
        str(PROBE_MEMORY_BYTES),
        str(MAX_SIDE),
        str(MAX_PIXELS),
        str(MAX_LEVELS),
    ]
    try:
        proc = subprocess.run(
            argv, capture_output=True, text=True, errors="replace", timeout=PROBE_TIMEOUT_S, stdin=subprocess.DEVNULL
        )
    except subprocess.TimeoutExpired:
        raise SlideError(
            path,
            f"OpenSlide did not open it within the {PROBE_TIMEOUT_S} s time limit of the separate process "
            "that opens a slide first (now stopped): a corrupt or hostile file, or one on a stalled disk",
        ) from None
    except OSError:
        return  # no child process here: open it in this one, as before
    if proc.returncode < 0:
        sig = -proc.returncode
        if sig == signal.SIGINT:
            raise KeyboardInterrupt
        name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else f"signal {sig}"
        said = [ln.strip() for ln in proc.stderr.splitlines() if ln.strip()]
        last = re.sub(r"^\(process:\d+\): |\b\d\d:\d\d:\d\d\.\d+: ", "", said[-1]) if said else ""
        why = f": {last[:200]}" if last else ""
        raise SlideError(
            path,
            f"OpenSlide crashed opening it ({name}{why}); it was opened in a separate process, so "
            "only that process stopped: a corrupt or hostile file, or sizes OpenSlide cannot "
            "hold in memory",
        )
    if proc.returncode == 0:
        _probed[key] = True


_ALIGN_TOLERANCE = 1e-3  # level px: OpenSlide's interpolation then moves a pixel by under 1/1000 of a step
_ALIGN_SEARCH = 4096  # level-0 px looked at below the corner


def _aligned_start(x: int, ds: float) -> tuple[int, int]:
    """``(X, g)``: a level-0 coordinate ``X`` with ``X / ds`` within :data:`_ALIGN_TOLERANCE` of the whole
    level pixel ``g <= x`` (the closest such ``g`` below ``x``; ``x`` itself when ``ds`` is a whole number),
    so that OpenSlide reads whole pixels from ``g`` on. Falls back to the best of :data:`_ALIGN_SEARCH`
    candidates (0 is always exact)."""
    if float(ds).is_integer():
        return int(x * ds), int(x)
    best = (1.0, int(x * ds), int(x))
    for big_x in range(math.floor(x * ds), max(-1, math.floor(x * ds) - _ALIGN_SEARCH), -1):
        pos = big_x / ds
        g = round(pos)
        if g > x:
            continue
        err = abs(pos - g)
        if err < best[0]:
            best = (err, big_x, g)
        if err <= _ALIGN_TOLERANCE:
            break
    return best[1], best[2]


def _on_white(rgba: np.ndarray) -> np.ndarray:
    """``(H, W, 4)`` uint8 RGBA (not premultiplied, as openslide-python returns it) over white → ``(H, W, 3)``."""
    alpha = rgba[..., 3:4]
    if alpha.min() == 255:
        return np.ascontiguousarray(rgba[..., :3])
    a = alpha.astype(np.float32) / 255.0
    out = rgba[..., :3].astype(np.float32) * a + 255.0 * (1.0 - a)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def _level_infos(slide, props) -> list[LevelInfo]:
    """LevelInfo of each OpenSlide level (finest first): its size, downsample and tile size."""
    infos = []
    for k, ((w, h), ds) in enumerate(zip(slide.level_dimensions, slide.level_downsamples)):
        tw, th = props.get(f"openslide.level[{k}].tile-width"), props.get(f"openslide.level[{k}].tile-height")
        tile = (int(tw), int(th)) if tw and th and tw.isdigit() and th.isdigit() else None
        infos.append(
            LevelInfo(width=int(w), height=int(h), downsample=float(ds), tile_size=tile, compression="openslide")
        )
    if not infos:
        raise SlideError(None, "OpenSlide reports no level")
    return infos


def _mpp(props) -> float | None:
    """µm per level-0 px: ``openslide.mpp-x`` (else ``mpp-y``), or None when absent or not a positive number."""
    for key in ("openslide.mpp-x", "openslide.mpp-y"):
        try:
            value = float(props.get(key, ""))
        except ValueError:
            continue
        if math.isfinite(value) and value > 0:
            return value
    return None
