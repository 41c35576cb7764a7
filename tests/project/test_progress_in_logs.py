"""A progress bar written to a log (not a terminal) is a few full lines, not carriage-return updates: was, 74 KB of
``\\r`` progress from ``learned_head_fit`` without ``--quiet`` in a log file."""

from __future__ import annotations

import io

from data_tools.cli_output import LineProgress, progress_bar


def test_a_log_gets_a_line_per_tenth_and_no_carriage_return():
    log = io.StringIO()  # not a terminal
    bar = progress_bar(range(5000), desc="64 units, seed 0", file=log)
    assert isinstance(bar, LineProgress)
    for i in bar:
        if i % 500 == 0:
            bar.set_postfix(loss="0.123", val="0.900")
    text = log.getvalue()
    assert "\r" not in text and len(text) < 2000
    lines = text.splitlines()  # the first step, then each tenth
    assert len(lines) == 11 and lines[-1].startswith("64 units, seed 0: 5000/5000 it (100 %), loss=0.123, val=0.900")


def test_update_and_close_say_the_end_once():
    log = io.StringIO()
    bar = progress_bar(total=3, desc="embedding b", unit="batch", file=log, initial=1)
    bar.update(1)
    bar.update(1)
    bar.close()
    bar.close()
    assert log.getvalue().splitlines()[-1].startswith("embedding b: 3/3 batch (100 %)")
    assert log.getvalue().count("3/3") == 1


def test_a_silent_bar_prints_nothing_and_a_terminal_gets_tqdm():
    log = io.StringIO()
    assert list(progress_bar(range(3), disable=True, file=log)) == [0, 1, 2] and log.getvalue() == ""

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    from tqdm import tqdm

    assert isinstance(progress_bar(range(3), file=Terminal()), tqdm)


def test_the_head_fit_and_the_feature_grid_use_it():
    import inspect

    from baselines.reading import learned_head_fit
    from data_tools.features import grid

    for module in (learned_head_fit, grid):
        assert "tqdm" not in inspect.getsource(module)
