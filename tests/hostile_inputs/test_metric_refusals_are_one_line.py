"""Scores no AUC can be measured on (:class:`data_tools.metrics.MetricInputError`: NaN or infinite scores, e.g. a
policy whose finite but extreme parameters overflow) reaching a command are one line, exit 2, through ``histojax``
and through ``python -m MODULE`` (:func:`data_tools.cli_output.command_main`, was: a traceback there)."""

from __future__ import annotations

import math

import pytest

from data_tools.cli_output import command_main
from data_tools.metrics import MetricInputError, roc_auc


def _scores_nan(args, parser=None) -> int:
    roc_auc([0.2, math.nan, 0.9], [0, 1, 1])  # a policy's p(tumour) gone NaN
    return 0


@pytest.mark.parametrize("scores", [[0.2, math.nan, 0.9], [0.2, math.inf, 0.9]])
def test_non_finite_scores_are_refused_by_the_metric(scores):
    with pytest.raises(MetricInputError, match="NaN or infinite scores"):
        roc_auc(scores, [0, 1, 1])


def test_a_module_command_turns_a_metric_refusal_into_one_line(capsys, monkeypatch):
    monkeypatch.delenv("HISTOJAX_DEBUG", raising=False)
    main = command_main(lambda p: None, _scores_nan, "python -m baselines.reading.example")
    assert main([]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "NaN or infinite scores" in err[0], err
    monkeypatch.setenv("HISTOJAX_DEBUG", "1")
    with pytest.raises(MetricInputError):  # the traceback kept for debugging
        main([])


def test_histojax_turns_a_metric_refusal_into_one_line(capsys, monkeypatch):
    from histojax import cli

    monkeypatch.delenv("HISTOJAX_DEBUG", raising=False)
    monkeypatch.setattr(cli, "_dispatch", lambda command, rest: _scores_nan(None))
    assert cli.main(["evaluate", "x"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "NaN or infinite scores" in err[0] and "HISTOJAX_DEBUG" not in err[0], err
