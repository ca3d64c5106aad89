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
        lag = solver._friction_lag_residual(which)  # moves friction's lag to u and back: the gradient at u is kept
        rhs, g_norm, load, change, energy = solver._read_gradient(which, True, True)
        trial = solver._energy_and_min_det(solver._u_try, which)
        return (rhs.numpy().copy(), g_norm, load, change, energy, trial, lag, solver._free_norm(solver._g),
                solver._max_penetration(which), solver._wrench(which))

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
    assert len({id(x) for x in [first, *later]}) == SOLUTIONS
    linear.cg_maxiter = 2  # a solve that does not converge returns None and takes no array
    assert linear.solve(solver._hessian(ind, 0.0, True), rhs, definite=True, rtol=1e-12) is None
    linear.cg_maxiter = 20000
    assert np.array_equal(first.numpy(), kept)
    again = linear.solve(solver._hessian(ind, 0.0, True), wp.array(0.5 * rhs.numpy(), dtype=wp.vec3d), rtol=1e-8)
    assert again is first and not np.array_equal(first.numpy(), kept)
