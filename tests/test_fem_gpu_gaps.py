"""scripts/fem_gpu_gaps.py's bookkeeping: the GPU's idle stretches inside the counted frames, the host's nested ranges
as a timeline of paths, and each idle microsecond charged to the path open at the time."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import fem_gpu_gaps  # noqa: E402
from fem_gpu_gaps import HostRange  # noqa: E402


def test_idle_stretches_merge_overlapping_activity_and_stay_inside_the_windows():
    busy = [(12.0, 20.0), (15.0, 25.0), (30.0, 31.0), (55.0, 70.0)]  # two streams overlap at 15-20
    assert fem_gpu_gaps.idle_stretches(busy, [(10.0, 40.0), (50.0, 60.0)]) == [
        (10.0, 12.0), (25.0, 30.0), (31.0, 40.0), (50.0, 55.0)]


def test_host_segments_follow_nesting_and_adjacent_ranges():
    ranges = [HostRange("newton", 0.0, 10.0), HostRange("gradient", 1.0, 4.0), HostRange("read", 3.0, 4.0),
              HostRange("hessian", 4.0, 6.0), HostRange("frame", 0.0, 12.0)]
    assert fem_gpu_gaps.host_segments(ranges) == [
        (0.0, 1.0, ("frame", "newton")), (1.0, 3.0, ("frame", "newton", "gradient")),
        (3.0, 4.0, ("frame", "newton", "gradient", "read")), (4.0, 6.0, ("frame", "newton", "hessian")),
        (6.0, 10.0, ("frame", "newton")), (10.0, 12.0, ("frame",))]


def test_idle_is_charged_by_overlap_and_the_uncovered_rest_to_no_range():
    segments = [(0.0, 2.0, ("a",)), (2.0, 5.0, ("a", "b")), (8.0, 9.0, ("c",))]
    charged = fem_gpu_gaps.idle_by_path([(1.0, 3.0), (4.0, 10.0)], segments)
    assert charged == pytest.approx({("a",): 1.0, ("a", "b"): 2.0, ("c",): 1.0, (): 4.0})
    assert sum(charged.values()) == pytest.approx(8.0)  # every idle microsecond once


def test_ranges_of_no_length_are_left_out():
    ranges = [HostRange("frame", 0.0, 4.0), HostRange("read", 2.0, 2.0), HostRange("gradient", 2.0, 3.0)]
    assert fem_gpu_gaps.host_segments(ranges) == [
        (0.0, 2.0, ("frame",)), (2.0, 3.0, ("frame", "gradient")), (3.0, 4.0, ("frame",))]


def test_marks_are_put_back_as_they_were():
    """The solver's methods, inherited ones included, and Warp's functions are their originals again afterwards; the
    marks name what they wrap."""
    import contextlib

    import warp as wp
    from fem_gpu_gaps import MARKED

    names = []

    @contextlib.contextmanager
    def record_function(name):
        names.append(name)
        yield

    before = {(cls, name): (cls.__dict__.get(name), getattr(cls, name)) for cls, ns in MARKED.items() for name in ns}
    launch, numpy = wp.launch, wp.array.numpy
    uninstall = fem_gpu_gaps.install_marks(record_function, warp_calls=True)
    try:
        assert wp.launch is not launch and wp.array.numpy is not numpy
        wp.copy(wp.zeros(3, dtype=float, device="cpu"), wp.ones(3, dtype=float, device="cpu"))
        assert names == ["wp.copy"]  # a CPU array's read is not marked: it waits for nothing
    finally:
        uninstall()
    assert wp.launch is launch and wp.array.numpy is numpy
    after = {(cls, name): (cls.__dict__.get(name), getattr(cls, name)) for cls, ns in MARKED.items() for name in ns}
    assert after == before
