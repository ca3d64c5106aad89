"""scripts/fem_host_census.py's bookkeeping: launches and copies counted by the transtac_sim call site that made them,
reads of host arrays not counted (no wait), the span between two reads charged to the read that ends it, and Warp's
functions put back afterwards."""

import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import fem_host_census  # noqa: E402

from transtac_sim.physics.reductions import max_abs  # noqa: E402


def test_calls_are_counted_by_call_site_and_the_originals_restored():
    launch, numpy = wp.launch, wp.array.numpy
    census = fem_host_census.Census()
    uninstall = fem_host_census.install(census)
    try:
        a = wp.array(np.arange(30.0).reshape(10, 3), dtype=wp.vec3d, device="cpu")
        census.counting = True
        assert max_abs(a) == 29.0
        wp.copy(wp.empty_like(a), a)
    finally:
        uninstall()
    assert wp.launch is launch and wp.array.numpy is numpy
    counts = {key: n for key, (n, _) in census.calls.items()}
    # the reduction's two passes, charged to where they were made; the copy, made outside the package, to "other"; no
    # read: a CPU array's read waits for nothing
    assert counts == {("launch", "reductions.py:_launch"): 2, ("copy", "other"): 1}, counts


def test_span_between_reads_is_charged_to_the_read_that_ends_it():
    census = fem_host_census.Census()
    census.counting = True
    census._span_start = 10.0
    census.record("launch", 10.5, 10.6)
    census.record("replay", 10.7, 10.8)
    census.record("read", 11.0, 11.4)  # called from this test module: site "other"
    reads, span, wait, ops = census.spans["other"]
    assert reads == 1 and np.isclose(span, 1.0) and np.isclose(wait, 0.4) and ops == 2
    census.record("read", 11.9, 12.0)  # the next span starts where the last read ended
    assert np.isclose(census.spans["other"][1], 1.5) and census.spans["other"][3] == 2
