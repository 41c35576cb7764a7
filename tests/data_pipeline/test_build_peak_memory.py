"""A bundle build records its own peak resident memory (``metadata["build"]["peak_rss_bytes"]``), not the lifetime
peak of the process that ran it: before, a build in a pytest worker recorded 4.26 GB (earlier tests' peak) and the
same figure at 20,000 and 100,000 px, failing the gigapixel test's 2 GB bound (data_tools.peak_memory)."""

from __future__ import annotations

import resource
import sys

import numpy as np
import pytest
import tifffile

from data_tools.bundle import build_bundle
from data_tools.bundle_files.reading import read_metadata
from data_tools.peak_memory import PeakRSS

SPIKE = 400 * 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self: Linux")
def test_a_build_after_a_memory_spike_records_its_own_peak(tmp_path):
    spike = np.ones(SPIKE // 8)  # earlier work in the process: 400 MiB resident, then freed
    del spike
    lifetime = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    image = np.full((512, 640, 3), 235, np.uint8)
    image[100:400, 120:500] = [190, 80, 150]
    tifffile.imwrite(tmp_path / "s.tif", image, photometric="rgb")
    out = build_bundle(
        tmp_path / "s.tif", tmp_path / "b", level_sets=(3,), tile_size=64, storage="tiled", progress=False
    )
    build = read_metadata(out)["build"]
    assert build["peak_rss_method"] in ("VmHWM", "sampled")
    assert 0 < build["peak_rss_bytes"] < lifetime - SPIKE // 2, (build, lifetime)


def test_peak_rss_sees_what_is_allocated_inside():
    with PeakRSS() as peak:
        block = np.ones(200 * 2**20 // 8)
        before = peak.bytes
        del block
    assert before is None and peak.method and peak.bytes >= 150 * 2**20
