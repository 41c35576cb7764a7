"""One-line messages for the command lines: user errors, warnings and library log records.

A command's stderr is then ``warning: ...`` lines (each once) followed, on a user error, by one
``error: ...`` line, with no traceback; the exit status of a user error is 2.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import re
import sys
import time
import warnings

USER_ERROR = 2
LOGGERS = ("tifffile", "imagecodecs")  # libraries whose log records would otherwise print free-form lines


_INSIDE_TEMPORARY = re.compile(r"(^|[/\\\s'\"(])\.([^/\\\s]+?)\.tmp-[0-9a-f]{8}(?=[/\\])")


def without_temporaries(text) -> str:
    """``text`` with every path inside one of histojax's hidden temporary folders (``bundles/.NAME.tmp-XXXXXXXX/
    metadata.json``, where a bundle is built before it is renamed into place) named by the folder it becomes
    (``bundles/NAME/metadata.json``): a user never sees the temporary, only the bundle."""
    return _INSIDE_TEMPORARY.sub(r"\1\2", str(text))


def one_line(text) -> str:
    """``text`` with every run of whitespace (newlines included) made one space, and paths inside a hidden
    temporary folder named by the folder it becomes (:func:`without_temporaries`)."""
    return " ".join(without_temporaries(text).split())


def print_error(error, hint: str = "") -> int:
    """Print ``error: <error>`` (one line) to stderr; returns the user-error exit status 2."""
    print(f"error: {one_line(error)}{hint}", file=sys.stderr)
    return USER_ERROR


def os_error_text(e: OSError) -> str:
    """``FILE: reason`` of an OSError, the way the project's own errors read."""
    where = e.filename if e.filename is not None else ""
    return f"{where}: {e.strerror or e}" if where else str(e.strerror or e)


class _LogToLine(logging.Handler):
    def __init__(self, emit):
        super().__init__(logging.WARNING)
        self._emit = emit

    def emit(self, record: logging.LogRecord) -> None:
        self._emit(f"{record.name}: {record.getMessage()}")


@contextlib.contextmanager
def one_line_messages(stream=None):
    """Within the block, warnings and the log records of ``LOGGERS`` print as one ``warning: ...`` line
    each on ``stream`` (default stderr), a repeated line only once."""
    stream = stream or sys.stderr
    seen: set[str] = set()

    def emit(text) -> None:
        line = f"warning: {one_line(text)}"
        if line not in seen:
            seen.add(line)
            print(line, file=stream)

    old_show = warnings.showwarning
    warnings.showwarning = lambda message, *args, **kwargs: emit(message)
    handler = _LogToLine(emit)
    loggers = [logging.getLogger(name) for name in LOGGERS]
    saved = [(lg.propagate, lg.handlers[:]) for lg in loggers]
    for lg in loggers:
        lg.handlers, lg.propagate = [handler], False
    try:
        yield
    finally:
        warnings.showwarning = old_show
        for lg, (propagate, handlers) in zip(loggers, saved):
            lg.handlers, lg.propagate = handlers, propagate


class OneLineParser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors are one ``error: PROG: ...`` line (exit status 2)."""

    def error(self, message):
        self.exit(USER_ERROR, f"error: {self.prog}: {one_line(message)} (--help shows the options)\n")


def finite_float(text: str) -> float:
    """argparse type: a finite number (``inf`` and ``nan`` refused)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} must be >= 1")
    return value


def seed_int(text: str) -> int:
    """argparse type: a random seed, an integer in ``[0, 2**32)`` (NumPy's generators refuse a negative one)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"{text!r} must be in [0, 2**32)")
    return value


# ----------------------------------------------------------------------------- one parser per command
def build_parser(
    add_arguments, prog: str | None = None, description: str | None = None, one_line: bool = True
) -> argparse.ArgumentParser:
    """The one place the project's command parsers are made: ``add_arguments(parser)`` — the command
    module's own function, the only place its options are declared — fills a new parser. Both
    ``histojax <command>`` and ``python -m <module>`` come here with the same function. ``one_line``:
    :class:`OneLineParser` (usage errors one line, exit 2: the ``histojax`` command and
    ``python -m data_tools``); ``False``: argparse's own usage and error lines (``python -m baselines.*``)."""
    parser_class = OneLineParser if one_line else argparse.ArgumentParser
    parser = parser_class(prog=prog, description=description)
    add_arguments(parser)
    return parser


_ROLE = re.compile(r":[a-z]+(?::[a-z]+)?:`(~?)([^`<]+?)(?:\s*<[^>]+>)?`")
_LITERAL = re.compile(r"``([^`]+)``")


def plain_text(doc: str | None) -> str:
    """``doc`` (a module's reST docstring) as a terminal shows help: roles (``:func:`~a.b``` → ``b``,
    ``:mod:`a.b``` → ``a.b``) and double backticks (````x```` → ``x``) written plain, the rest as it is."""

    def role(m: re.Match) -> str:
        target = m.group(2).strip()
        return target.rsplit(".", 1)[-1] if m.group(1) else target

    return _LITERAL.sub(r"\1", _ROLE.sub(role, doc or ""))


def run_command(
    add_arguments, run, argv=None, prog: str | None = None, doc: str | None = None, one_line: bool = True
) -> int:
    """Run a command: ``add_arguments(parser)`` declares its options, ``run(args, parser) -> int`` runs
    it on the parsed ``args`` (``parser.error`` for usage errors found after parsing). Parses ``argv``
    (default ``sys.argv[1:]``) with :func:`build_parser`, described by the first paragraph of ``doc``
    (the command module's doc); returns the exit status. Every command module's ``main`` and the
    ``histojax`` command call it with the module's two functions."""
    description = plain_text((doc or "").split("\n\n")[0]) or None  # no reST markup on the terminal
    parser = build_parser(add_arguments, prog, description, one_line)
    return int(run(parser.parse_args(argv), parser) or 0)


def command_main(add_arguments, run, prog: str, doc: str | None = None, one_line: bool = False):
    """A command module's ``main(argv=None) -> int`` (``python -m MODULE``): :func:`run_command` with
    the module's ``add_arguments`` and ``run``; ``histojax <command>`` calls the same two functions. A
    ``HistojaxDataError`` that reaches it (a malformed file found where the command does not catch it) or a
    :class:`~data_tools.metrics.MetricInputError` (NaN or infinite scores given to an AUC) is one line, exit 2, as
    ``histojax`` says it (``HISTOJAX_DEBUG=1``: the traceback)."""

    def main(argv=None) -> int:
        import os

        from data_tools.errors import HistojaxDataError
        from data_tools.metrics import MetricInputError

        try:
            return run_command(add_arguments, run, argv, prog=prog, doc=doc, one_line=one_line)
        except (HistojaxDataError, MetricInputError) as e:  # a bad file found deep inside (a dataset.json, a
            # bundle), or scores no figure can be measured on (NaN from a policy): one line, exit 2
            if os.environ.get("HISTOJAX_DEBUG"):
                raise
            return print_error(e)

    main.__doc__ = f"``{prog}``: parse ``argv`` (default ``sys.argv[1:]``) and run; returns the exit status."
    return main


def add_reader_argument(p) -> None:
    """``--reader auto|native|openslide`` on the parser ``p`` (``info``, ``build``, ``dataset``)."""
    p.add_argument(
        "--reader",
        choices=("auto", "native", "openslide"),
        default="auto",
        help="what reads the slides: auto (default: tifffile / wsidicom, OpenSlide for MIRAX, SCN, BIF, "
        "VMS / VMU, SVSlide and Philips TIFF), native, or openslide (any slide through OpenSlide 4; "
        "pip install 'histojax[openslide]')",
    )


class LineProgress:
    """A progress bar for a stream that is not a terminal (a log file, a pipe): a full line at every tenth of
    ``total`` (and at the end), never carriage-return updates; :func:`progress_bar`'s. The tqdm calls the tools
    make: iteration, ``update``, ``set_postfix``, ``close`` (and ``with``)."""

    def __init__(self, iterable=None, desc: str = "", total=None, file=None, initial: int = 0, unit: str = "it"):
        self.iterable, self.desc, self.file, self.unit = iterable, desc, file or sys.stderr, unit
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total, self.n, self.postfix, self.shown = total, int(initial), "", -1
        self.t0 = time.perf_counter()

    def __iter__(self):
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def set_postfix(self, ordered_dict=None, refresh: bool = True, **kwargs) -> None:
        """Shown at the end of the next line (as tqdm's postfix: ``key=value``)."""
        items = {**(ordered_dict or {}), **kwargs}
        self.postfix = ", ".join(f"{k}={v}" for k, v in items.items())

    def update(self, n: int = 1) -> None:
        """``n`` more done: a line when a new tenth of ``total`` is reached (unknown total: every 10 % of a
        power of ten)."""
        self.n += int(n)
        tenth = int(10 * self.n / self.total) if self.total else int(math.log10(max(self.n, 1)) * 10)
        if tenth > self.shown:
            self.shown = tenth
            self._line()

    def close(self) -> None:
        """The last line, once (when the last update did not print it)."""
        if self.shown < 10 and self.total and self.n >= self.total:
            self.shown = 10
            self._line()
        self.shown = max(self.shown, 10)

    def _line(self) -> None:
        of = f"/{self.total}" if self.total else ""
        pct = f" ({100 * self.n / self.total:.0f} %)" if self.total else ""
        took = time.perf_counter() - self.t0
        tail = f", {self.postfix}" if self.postfix else ""
        print(f"{self.desc}: {self.n}{of} {self.unit}{pct}{tail}, {took:.0f} s", file=self.file, flush=True)


def progress_bar(iterable=None, desc: str = "", total=None, disable: bool = False, file=None, **kwargs):
    """tqdm on a terminal; on any other stream (a log, a pipe) a :class:`LineProgress` (a full line at every tenth,
    no carriage returns filling the log). ``disable``: tqdm's silent bar. Other keywords go to tqdm (``unit``,
    ``initial`` are kept by both)."""
    file = file if file is not None else sys.stderr
    if disable or (hasattr(file, "isatty") and file.isatty()):
        from tqdm import tqdm

        return tqdm(iterable, desc=desc, total=total, disable=disable, file=file, **kwargs)
    return LineProgress(iterable, desc, total, file, kwargs.get("initial", 0), kwargs.get("unit", "it"))
