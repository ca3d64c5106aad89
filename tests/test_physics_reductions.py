"""The Newton loop's device reductions (physics/reductions.py) against numpy: exact for maxima and minima, to round-off
for sums; NaN and infinity handled as the numpy code they replace handled them; the same bits on every run."""

import numpy as np
import pytest
import warp as wp

from transtac_sim.physics.reductions import (
    extremes,
    launch_extremes,
    max_abs,
    negated_free,
    negated_free_and_load,
    read_extremes,
    reduction_buffer,
    step_summary,
)

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() else [])
N = 3001  # not a multiple of the block's 256 threads


def _vec(a: np.ndarray, device) -> wp.array:
    return wp.array(a, dtype=wp.vec3d, device=device)


@pytest.mark.parametrize("device", DEVICES)
def test_max_abs_is_numpys(device):
    a, b = np.random.default_rng(3).standard_normal((2, N, 3))
    b[123, 1] = a[123, 1] + 7.5  # the largest difference, in one component of one node
    got = max_abs(_vec(a, device), _vec(b, device))
    assert got == np.max(np.abs(a - b)) and abs(got - 7.5) < 1e-12
    a[2999, 2] = -9.25  # the largest entry, negative
    assert max_abs(_vec(a, device)) == 9.25
    a[5, 0] = np.nan  # NaN wins, as in numpy's max: a broken step or estimate is never taken as short
    assert np.isnan(max_abs(_vec(a, device))) and np.isnan(max_abs(_vec(b, device), _vec(a, device)))


@pytest.mark.parametrize("device", DEVICES)
def test_extremes_are_numpys_and_nan_wins(device):
    x = np.random.default_rng(4).standard_normal(4 * N)
    assert extremes(wp.array(x, dtype=wp.float64, device=device)) == (x.min(), x.max())
    x[17] = np.nan  # det F of a broken state: min(det F) > 0 must then be False, as with numpy's NaN
    low, high = extremes(wp.array(x, dtype=wp.float64, device=device))
    assert np.isnan(low) and np.isnan(high) and not low > 0.0
    with pytest.raises(ValueError, match="empty"):
        extremes(wp.empty(0, dtype=wp.float64, device=device))


@pytest.mark.parametrize("device", DEVICES)
def test_negated_free_zeroes_the_fixed_components(device):
    rng = np.random.default_rng(5)
    g = rng.standard_normal((N, 3))
    fixed = (rng.random((N, 3)) < 0.3).astype(np.float64)
    rhs, norm = negated_free(_vec(g, device), _vec(fixed, device))
    expected = -g * (1.0 - fixed)
    assert np.array_equal(rhs.numpy(), expected)
    assert norm == pytest.approx(np.linalg.norm(expected), rel=1e-14)
    _, same, load = negated_free_and_load(_vec(g, device), _vec(fixed, device))
    assert same == norm and load == pytest.approx(abs(g[fixed[:, 2] > 0.5, 2].sum()), rel=1e-12)  # the support's load
    _, zero = negated_free(_vec(g, device), _vec(np.ones((N, 3)), device))
    assert zero == 0.0  # every component fixed: Newton's "already at equilibrium"
    g[np.flatnonzero(fixed[:, 0])[0], 0] = np.inf  # whatever a fixed component holds, it is dropped
    rhs, again = negated_free(_vec(g, device), _vec(fixed, device))
    assert np.array_equal(rhs.numpy(), expected) and again == norm


@pytest.mark.parametrize("device", DEVICES)
def test_step_summary_slope_length_and_sanity(device):
    rng = np.random.default_rng(6)
    du, rhs = rng.standard_normal((2, N, 3))
    dot, largest, finite = step_summary(_vec(du, device), _vec(rhs, device))
    assert dot == pytest.approx(np.sum(du * rhs), rel=1e-13) and largest == np.max(np.abs(du)) and finite
    again = step_summary(_vec(du, device), _vec(rhs, device))
    assert again == (dot, largest, finite)  # partials combined in a fixed order, no atomics: the same bits every run
    for bad in (np.nan, np.inf, -np.inf):
        broken = du.copy()
        broken[77, 0] = bad
        assert step_summary(_vec(broken, device), _vec(rhs, device))[2] is False


@pytest.mark.parametrize("blocks", [7, 128, 4096])
def test_partials_of_several_blocks_combine_to_numpys(blocks, monkeypatch):
    """The first pass over several thread blocks (a GPU's; here on the CPU, where a block is one thread), their partial
    results combined by ``_combine``: maxima, minima and NaN counts exact, sums to round-off, the same bits on every
    run. With 4096 blocks for 3001 entries some blocks get none: their partials are the combination's identity, which
    must not win on data all of one sign."""
    from transtac_sim.physics import reductions

    monkeypatch.setattr(reductions, "reduction_blocks", lambda device: blocks)
    rng = np.random.default_rng(7)
    a, b, fixed = rng.standard_normal((3, N, 3))
    fixed = (fixed > 0.5).astype(np.float64)
    assert max_abs(_vec(a, "cpu"), _vec(b, "cpu")) == np.max(np.abs(a - b))
    for x in (rng.standard_normal(N), rng.uniform(2.0, 3.0, N), rng.uniform(-3.0, -2.0, N)):
        assert extremes(wp.array(x, dtype=wp.float64, device="cpu")) == (x.min(), x.max())
    rhs, norm = negated_free(_vec(a, "cpu"), _vec(fixed, "cpu"))
    assert norm == pytest.approx(np.linalg.norm(-a * (1.0 - fixed)), rel=1e-14)
    summary = step_summary(_vec(a, "cpu"), _vec(b, "cpu"))
    assert summary[0] == pytest.approx(np.sum(a * b), rel=1e-13) and summary[1] == np.max(np.abs(a)) and summary[2]
    assert step_summary(_vec(a, "cpu"), _vec(b, "cpu")) == summary
    a[2000, 1] = np.nan
    assert np.isnan(max_abs(_vec(a, "cpu"))) and step_summary(_vec(a, "cpu"), _vec(b, "cpu"))[2] is False


def test_a_buffer_too_small_for_the_partials_is_refused():
    from transtac_sim.physics.reductions import launch_extremes

    with pytest.raises(ValueError, match="reduction_buffer"):
        launch_extremes(wp.array(np.ones(10), dtype=wp.float64, device="cpu"),
                        wp.empty(3, dtype=wp.float64, device="cpu"))


@pytest.mark.parametrize("device", DEVICES)
def test_callers_scalars_are_read_with_a_reduction(device):
    """``negated_free_and_load``'s ``also`` and ``read_extremes``'s ``also``: values the caller copied next to the
    results come back with them in the same read (newton.py: the barrier's energy and friction's lag distance with |g|;
    assembly.py: E with the line search's det F), the results unchanged."""
    rng = np.random.default_rng(8)
    g = rng.standard_normal((N, 3))
    fixed = (rng.random((N, 3)) < 0.3).astype(np.float64)
    one, two = (wp.array(v, dtype=wp.float64, device=device) for v in ([2.5, 9.0], [-1.0, 4.0, 7.0]))
    plain = negated_free_and_load(_vec(g, device), _vec(fixed, device))
    rhs, norm, load, a, b, c = negated_free_and_load(_vec(g, device), _vec(fixed, device), ((one, 1), (two, 2)))
    assert (norm, load) == plain[1:] and (a, b, c) == (2.5, -1.0, 4.0)
    assert np.array_equal(rhs.numpy(), plain[0].numpy())
    x = rng.standard_normal(N)
    out = reduction_buffer(3, device)
    launch_extremes(wp.array(x, dtype=wp.float64, device=device), out)
    wp.copy(out, two, dest_offset=3, count=2)
    assert read_extremes(out, also=2) == ((x.min(), x.max()), [-1.0, 4.0])
