"""Two processes for real: ``benchmarks/two_process.py`` starts PPO as 2 ``jax.distributed``
processes on 127.0.0.1 (gloo CPU collectives, one CPU device each, the 8 slides split 4 + 4 with
``--shard-slides``), then the same command as one process with 2 fake devices. Asserted: both
processes exit 0 within the timeout (the script kills them otherwise), each holds 4 slides, both
end with identical parameters, and those agree with the one-process run. ~1–2 minutes of
compiling on 2 cores, hence slow-marked (``make test-all``)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_two_processes_train_the_same_parameters(small_slides, tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "two_process.py"),
            "--compare-single",
            "--fast-compile",
            "--timeout",
            "500",
            "--out",
            str(tmp_path),
            "--slides",
            *small_slides,
        ],
        env=env,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    out = proc.stdout
    assert proc.returncode == 0, out[-4000:] + proc.stderr[-4000:]
    assert "process 0 of 2: 4 slide(s)" in out and "process 1 of 2: 4 slide(s)" in out
    assert "process 1 parameters identical to process 0's" in out
    assert "(agree)" in out and out.rstrip().endswith("OK")
