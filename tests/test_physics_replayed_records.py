"""The launch sequences replayed as CUDA graphs to save host operations (BENCHMARKS.md ``fem_host_operations_gpu``):
Newton's gradient read and line-search trial, |g| at a frame's end, friction's lag update and residual, the largest
penetration, the wrench, and the device solve's set-up. Each replay reads the current values and gives what the same
methods give with a graph cache that only launches. On the CPU (no graphs) the cases check the launch path only; the
replays are checked by the CUDA cases (the device tool, not CI)."""

import numpy as np
import pytest
import warp as wp
from test_physics_sparse_product import DEVICES, _launched, _next_step, _pressed_solver

from transtac_sim.physics.device_linear import SOLUTIONS
from transtac_sim.physics.linear import LinearSolver


@pytest.mark.parametrize("device", DEVICES)
def test_replayed_reads_and_contact_records_equal_the_launched_ones(device):
    solver, ind = _pressed_solver(device=device)
    u0 = solver.u.dof_values.numpy().copy()
    replaying = solver._graphs

    def evaluate(which):
        # launched as solve_frame launches them, then read: friction's lag moved to u and back (the gradient at u is
        # kept), and the wrench
        lagged = solver._launch_friction_lag_residual(which)
        solver._launch_wrench(which)
        lag, wrench = solver._read_free_norm() if lagged else 0.0, solver._read_wrench()
        rhs, g_norm, load, change, energy = solver._read_gradient(which, True, True)
        trial = solver._energy_and_min_det(solver._u_try, which)
        return (rhs.numpy().copy(), g_norm, load, change, energy, trial, lag, solver._free_norm(solver._g),
                solver._max_penetration(which), wrench)

    replaying.clear()
    got, expected, captured = [], [], []
    for scale in (1.0, 0.9, 0.95, 0.85):  # the first call launches, the second captures, the rest replay
        captured.append(replaying.captures)
        solver.u.dof_values.assign(scale * u0)
        solver.u_lag.dof_values.assign(0.9 * scale * u0)  # a lag behind u
        solver._u_try.dof_values.assign(1.02 * scale * u0)
        solver._update_lag(ind)
        got.append(evaluate(ind))
        expected.append(_launched(solver, evaluate, ind))
    step = _next_step(solver)  # the next load step's poses, written into the same struct: replayed
    got.append(evaluate(step))
    expected.append(_launched(solver, evaluate, step))
    def scalars(values):  # E and det F are None where the CPU leaves them to their callers
        return [v for v in (*values[1:5], *values[5], *values[6:9]) if v is not None]

    for g, e in zip(got, expected, strict=True):
        np.testing.assert_allclose(g[0], e[0], rtol=0, atol=1e-12 * np.abs(e[0]).max())
        assert len(scalars(g)) == len(scalars(e)) == (9 if solver.device.is_cuda else 7)
        np.testing.assert_allclose(scalars(g), scalars(e), rtol=1e-12)
        np.testing.assert_allclose(g[9], e[9], rtol=1e-12, atol=1e-15)
    assert len({g[1] for g in got}) == len(got)  # every state gave its own |g|
    assert len({float(g[9][0, 2]) for g in got}) == len(got)  # and its own normal force
    assert all(g[6] > 0.0 and g[8] > 0.0 for g in got)  # friction's lag left a residual; the sphere penetrates
    if solver.device.is_cuda:  # every graph captured by the second state; the later states and poses replay them
        assert captured[2] > captured[1] and replaying.captures == captured[2], (captured, replaying.captures)


@pytest.mark.parametrize("device", DEVICES)
def test_the_gradient_that_takes_the_trial_starts_from_it(device):
    """newton.py's accepted line-search trial is copied into u by the next gradient (``take_trial``; inside its graph
    on a GPU): u becomes u_try, and the gradient, |g| and the load are those at u_try, for each state replayed."""
    solver, ind = _pressed_solver(device=device)
    u0 = solver.u.dof_values.numpy().copy()
    replaying = solver._graphs
    replaying.clear()  # the graphs of the solve that made the state

    def evaluate(which):
        rhs, g_norm, load, _, _ = solver._read_gradient(which, False, False, take_trial=True)
        return rhs.numpy().copy(), g_norm, load, solver.u.dof_values.numpy().copy()

    captured = []
    for scale in (1.0, 0.9, 0.95, 0.85):  # launched, captured, then replayed
        captured.append(replaying.captures)
        trial = 1.02 * scale * u0
        solver.u.dof_values.assign(0.5 * u0)  # not where the gradient is taken
        solver._u_try.dof_values.assign(trial)
        got = evaluate(ind)
        solver.u.dof_values.assign(0.5 * u0)
        expected = _launched(solver, evaluate, ind)
        np.testing.assert_array_equal(got[3], trial)
        np.testing.assert_array_equal(expected[3], trial)
        np.testing.assert_allclose(got[0], expected[0], rtol=0, atol=1e-12 * np.abs(expected[0]).max())
        np.testing.assert_allclose(got[1:3], expected[1:3], rtol=1e-12)
        solver.u.dof_values.assign(trial)  # the gradient at u_try taken as it is
        _, g_norm, load, _, _ = solver._read_gradient(ind, False, False)
        np.testing.assert_allclose((g_norm, load), got[1:3], rtol=1e-12)
    if solver.device.is_cuda:
        assert captured[2] > captured[1] and replaying.captures == captured[2], (captured, replaying.captures)


@pytest.mark.parametrize("device", DEVICES)
def test_the_trial_graph_reads_the_step_and_alpha_it_is_given(device):
    """trial_point.py ``_try_step``: on a GPU, where du is one of the linear solver's kept solutions, the trial point
    is launched in the energy's graph, which reads du's row and alpha at each replay: u_try, E and det F equal those of
    the trial point launched on its own (``_set_trial``) for each (row, alpha), with one graph for all of them. On the
    CPU the trial point is always launched on its own; its case checks that path."""
    solver, ind = _pressed_solver(device=device)
    u0 = solver.u.dof_values.numpy().copy()
    linear = LinearSolver("cg", solver._fixed_nodes, solver.device)
    solver._linear = linear
    rhs = wp.array(-solver._gradient(ind).numpy(), dtype=wp.vec3d, device=solver.device)
    steps = [linear.solve(solver._hessian(ind, 0.0, True), wp.array(k * rhs.numpy(), dtype=wp.vec3d,
                                                                     device=solver.device), rtol=1e-8)
             for k in (1.0, -0.5, 0.25)]
    replaying = solver._graphs
    replaying.clear()
    captured = []
    for du, alpha in [(steps[0], 1.0), (steps[1], 0.5), (steps[2], 0.25), (steps[0], 0.125), (steps[1], 1.0)]:
        captured.append(replaying.captures)
        got = solver._try_step(du, alpha, ind), solver._u_try.dof_values.numpy().copy()
        solver._u_try.dof_values.zero_()
        solver._set_trial(du, alpha)
        expected = solver._energy_and_min_det(solver._u_try, ind), solver._u_try.dof_values.numpy().copy()
        np.testing.assert_allclose(got[1], expected[1], rtol=0, atol=1e-15 * np.abs(u0).max())
        np.testing.assert_allclose(got[1], u0 + alpha * du.numpy(), rtol=0, atol=1e-15 * np.abs(u0).max())
        assert (got[0][1] is None) == (expected[0][1] is None) == (not solver.device.is_cuda)
        np.testing.assert_allclose([v for v in got[0] if v is not None], [v for v in expected[0] if v is not None],
                                   rtol=1e-12)
    if solver.device.is_cuda:  # the kept-step graph captured at its second use, then replayed for every row and alpha
        assert captured[2] > captured[1] and replaying.captures == captured[2], (captured, replaying.captures)


@pytest.mark.parametrize("device", DEVICES)
def test_frame_records_launched_together_equal_each_read_on_its_own(device):
    """load_stepping.py ``_frame_records``: friction's lag residual, the wrench and the smallest det F launched together
    and then read equal each launched and read on its own (no launch overwrites what another reads), for changed
    states."""
    solver, ind = _pressed_solver(device=device)
    u0 = solver.u.dof_values.numpy().copy()
    for scale in (1.0, 0.9, 0.95):  # launched, captured, then replayed
        solver.u.dof_values.assign(scale * u0)
        solver.u_lag.dof_values.assign(0.9 * scale * u0)  # a lag behind u
        solver._update_lag(ind)
        lag, wrench, min_det = solver._frame_records(ind)
        solver._launch_friction_lag_residual(ind)
        alone_lag = solver._read_free_norm()
        solver._launch_wrench(ind)
        alone_wrench = solver._read_wrench()
        alone_min_det = solver._min_det(solver.u)
        assert lag > 0.0 and min_det > 0.0 and np.abs(wrench).max() > 0.0
        np.testing.assert_allclose([lag, min_det], [alone_lag, alone_min_det], rtol=1e-12)
        np.testing.assert_allclose(wrench, alone_wrench, rtol=1e-12, atol=1e-15)


def test_free_norm_refuses_a_vector_of_another_mesh():
    solver, _ = _pressed_solver()
    with pytest.raises(ValueError, match="a gradient of 5 nodes"):
        solver._free_norm(wp.zeros(5, dtype=wp.vec3d))


@pytest.mark.parametrize("device", DEVICES)
def test_replayed_solve_set_up_solves_each_new_system(device):
    """The device solve's set-up (projection, float32 copy, diagonal inverses, x = 0; device_linear.py ``_solve_cg``)
    replayed for the solver's one Hessian matrix sees its new values: each solve of a changed system equals the first
    solve of that system by a fresh linear solver (whose set-up is launched)."""
    solver, ind = _pressed_solver(device=device)
    u0 = solver.u.dof_values.numpy().copy()
    kept = LinearSolver("cg", solver._fixed_nodes, solver.device)
    for scale in (1.0, 0.9, 0.95, 0.85):  # launched, captured, then replayed
        solver.u.dof_values.assign(scale * u0)
        rhs = wp.array(-solver._gradient(ind).numpy(), dtype=wp.vec3d, device=solver.device)
        x = kept.solve(solver._hessian(ind, 0.0, True), rhs, rtol=1e-10).numpy().copy()
        fresh = LinearSolver("cg", solver._fixed_nodes, solver.device)
        x_ref = fresh.solve(solver._hessian(ind, 0.0, True), rhs, rtol=1e-10).numpy()
        np.testing.assert_allclose(x, x_ref, rtol=0, atol=1e-8 * np.abs(x_ref).max())
        assert np.abs(x).max() > 0.0


def test_device_solutions_are_kept_arrays_taken_in_turn():
    """device_linear.SOLUTIONS: each device solution is returned in the next of that many kept arrays; one stays as it
    was until that many more solutions have been returned, and a solve that returns None takes none."""
    solver, ind = _pressed_solver()
    linear = LinearSolver("cg", solver._fixed_nodes, solver.device)
    rhs = wp.array(-solver._gradient(ind).numpy(), dtype=wp.vec3d)
    first = linear.solve(solver._hessian(ind, 0.0, True), rhs, rtol=1e-8)
    kept = first.numpy().copy()
    later = []
    for k in range(1, SOLUTIONS):
        later.append(linear.solve(solver._hessian(ind, 0.0, True), wp.array((1.0 + k) * rhs.numpy(), dtype=wp.vec3d),
                                  rtol=1e-8))
        assert np.array_equal(first.numpy(), kept)  # not overwritten yet
    assert len({x.ptr for x in [first, *later]}) == SOLUTIONS
    rows = [linear.solution_row(x) for x in [first, *later]]  # where a graph finds each of them
    assert [row for _, row in rows] == list(range(SOLUTIONS)) and all(a is rows[0][0] for a, _ in rows)
    assert linear.solution_row(rhs) is None and linear.solution_row(wp.clone(first)) is None
    linear.cg_maxiter = 2  # a solve that does not converge returns None and takes no array
    assert linear.solve(solver._hessian(ind, 0.0, True), rhs, definite=True, rtol=1e-12) is None
    linear.cg_maxiter = 20000
    assert np.array_equal(first.numpy(), kept)
    again = linear.solve(solver._hessian(ind, 0.0, True), wp.array(0.5 * rhs.numpy(), dtype=wp.vec3d), rtol=1e-8)
    assert again.ptr == first.ptr and not np.array_equal(first.numpy(), kept)
