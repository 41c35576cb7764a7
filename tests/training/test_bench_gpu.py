"""``benchmarks/gpu.py`` (``make bench-gpu``) runs on a CPU at tiny sizes and writes every section:
a positive figure or an explicit reason for skipping it. No speed is asserted."""

from __future__ import annotations

import json
import math

import pytest

from benchmarks import gpu

SECTIONS = (
    "copy",
    "env_pixels",
    "env_features",
    "ppo_features",
    "ppo_pixels",
    "encoders",
    "dataset_features",
    "dataset_pixels",
)


def _numbers(section: dict) -> list[float]:
    """The rates of a measured section."""
    if "rows" in section:
        return [r["steps_per_s"] for r in section["rows"]]
    if "bytes_per_s" in section:
        return [section["bytes_per_s"]]
    if "steps_per_s" in section:
        return [section["steps_per_s"], section["env_steps"]]
    return [section["views_per_s"]]


def _check(report: dict, allow_skips: bool = True) -> None:
    for name in SECTIONS:
        section = report[name]
        parts = section.items() if name == "encoders" and "skipped" not in section else [(name, section)]
        for part, sec in parts:
            if "skipped" in sec:
                assert allow_skips and isinstance(sec["skipped"], str) and sec["skipped"].strip(), (part, sec)
                continue
            numbers = _numbers(sec)
            assert numbers and all(math.isfinite(x) and x > 0 for x in numbers), (part, sec)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("gpu")
    argv = ["--tiny", "--max-batch", "1", "--dataset-max-batch", "1", "--env", "HistoJAX-Easy-v0", "--out", str(out)]
    assert gpu.main(argv) == 0
    return out, json.loads((out / "gpu.json").read_text()), (out / "gpu.md").read_text()


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_every_section_has_figures_or_a_reason(tiny_run):
    _, report, md = tiny_run
    _check(report)
    # on a CPU with --tiny, only EfficientNet is skipped: everything else was measured
    measured = [s for s in SECTIONS if s != "encoders"]
    assert not [s for s in measured if "skipped" in report[s]], {s: report[s] for s in measured}
    assert "skipped" in report["encoders"]["efficientnet-lite0"]
    assert report["encoders"]["colour-stats"]["views_per_s"] > 0
    assert set(gpu.encoder_names()) == set(report["encoders"])
    assert report["dataset_features"]["device_bytes"] > 0 and report["dataset_pixels"]["device_bytes"] > 0
    assert report["dataset_pixels"]["device_bytes"] > report["dataset_features"]["device_bytes"]
    row = report["env_pixels"]["rows"][0]
    assert row["copy_bound_views_per_s"] > 0 and row["of_copy_bound"] > 0
    m = report["machine"]
    assert m["jax"] and m["jaxlib"] and "--tiny" in m["command"] and m["platform"] == "cpu"
    for title in (
        "Memory-copy bound",
        "pixel observations",
        "feature observations",
        "PPO end to end",
        "Encoders",
        "C16 dataset, feature mode",
        "C16 dataset, pixel mode",
    ):
        assert title in md


@pytest.mark.slow  # `make test-all`; keeps `make test` under 10 minutes on 2 cores
def test_the_checker_can_fail(tiny_run):
    _, report, _ = tiny_run
    broken = json.loads(json.dumps(report))
    broken["ppo_pixels"]["steps_per_s"] = 0.0
    with pytest.raises(AssertionError):
        _check(broken)
    broken = json.loads(json.dumps(report))
    broken["dataset_pixels"] = {"skipped": " "}
    with pytest.raises(AssertionError):
        _check(broken)


def test_spent_budget_skips_the_rest_and_says_so(tmp_path):
    assert gpu.main(["--tiny", "--time-budget", "1e-9", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "gpu.json").read_text())
    _check(report)
    assert all("time budget spent" in report[s]["skipped"] for s in SECTIONS)
    assert "skipped" in (tmp_path / "gpu.md").read_text()


def test_batches_and_oom_detection():
    assert gpu.batches_up_to(65536) == [1, 4, 16, 64, 256, 1024, 4096, 16384, 65536]
    assert gpu.batches_up_to(1) == [1] and gpu.batches_up_to(20) == [1, 4, 16, 20]
    assert gpu.is_oom(RuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 3.2GiB"))
    assert not gpu.is_oom(ValueError("shapes do not match"))


def test_out_of_memory_stops_the_growth_and_says_so(monkeypatch):
    """A batch that runs out of device memory ends the sweep with the reason; larger ones are not tried."""
    tried = []

    def fake_measure(env, params, batch, env_steps, seconds):
        tried.append(batch)
        if batch >= 64:
            raise RuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 12345 bytes.")
        return {"steps_per_s": 10.0 * batch, "first_call_s": 0.1}

    monkeypatch.setattr(gpu, "measure", fake_measure)
    args = gpu._with(gpu.argparse_defaults(), max_batch=4096)
    table = gpu.env_rows(None, None, args, gpu.Budget(100), 49152, 1e9)
    assert tried == [1, 4, 16, 64]
    assert [r["batch"] for r in table["rows"]] == [1, 4, 16]
    assert "batch 64: out of device memory" in table["stopped"]
    monkeypatch.setattr(gpu, "measure", lambda *a: (_ for _ in ()).throw(ValueError("a real bug")))
    with pytest.raises(ValueError):
        gpu.env_rows(None, None, args, gpu.Budget(100), None, None)
