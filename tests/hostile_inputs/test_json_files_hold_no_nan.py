"""No JSON file histojax writes holds ``NaN`` or ``Infinity`` (not JSON; many readers refuse it): every
``json.dump`` / ``json.dumps`` of the packages passes ``allow_nan=False``, undefined figures go through
:func:`data_tools.metrics.json_safe` (``null``), and the readers' ``readers.json`` of a split whose AUC without
ITC-only slides is undefined holds ``null`` there."""

from __future__ import annotations

import ast
import json
import math
from pathlib import Path

import numpy as np
import pytest

from data_tools.metrics import json_safe

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("histojax", "baselines", "data_tools", "experiments")
NOT_WRITTEN = "json-not-written"
"""A comment on a ``json.dumps`` line whose text is never written to a file (a hash, a cache key, a message)."""


def _dump_calls(path: Path):
    text = path.read_text()
    lines = text.splitlines()
    for node in ast.walk(ast.parse(text)):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr in ("dump", "dumps")
            and isinstance(node.func.value, ast.Name)
            and node.func.value.id == "json"
        ):
            # the marker may stand on any line of the call (the formatter wraps long calls)
            yield node, "\n".join(lines[node.lineno - 1 : node.end_lineno])


def _writes(line: str, node) -> bool:
    """Whether a dump's text can end up in a file: not a message (inside an f-string / error), not a hash or key."""
    return NOT_WRITTEN not in line and "[:60]" not in line


def test_every_json_file_written_refuses_nan():
    missing = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node, line in _dump_calls(path):
                allow = [k for k in node.keywords if k.arg == "allow_nan"]
                ok = allow and isinstance(allow[0].value, ast.Constant) and allow[0].value.value is False
                if not ok and _writes(line, node):
                    missing.append(f"{path.relative_to(ROOT)}:{node.lineno}: {line.splitlines()[0].strip()}")
    assert not missing, "json.dump without allow_nan=False (use data_tools.metrics.json_safe):\n" + "\n".join(missing)


def test_json_safe_turns_undefined_figures_into_null():
    record = {
        "auc": float("nan"),
        "rows": [np.float32(np.inf), np.float64(0.5), (1, np.int64(2))],
        "per_seed": np.asarray([[1.0, np.nan]]),
        "ok": np.bool_(True),
        "name": "x",
    }
    text = json.dumps(json_safe(record), allow_nan=False)
    back = json.loads(text)
    assert back == {"auc": None, "rows": [None, 0.5, [1, 2]], "per_seed": [[1.0, None]], "ok": True, "name": "x"}
    assert math.isnan(np.asarray(back["per_seed"], float)[0, 1])  # read back as numbers, null is NaN again
    with pytest.raises(ValueError):
        json.dumps(record["auc"], allow_nan=False)
