"""scripts/fem_coupled_friction.py: its coupling term is the derivative of friction's gradient through the normal
pressure (checked against central differences of the gradient with the lag at u); its Newtons (host LU, device Krylov,
lagged first, nonmonotone) end at the lag's fixed point; ``lag_contraction`` is rho(H^-1 J_c) and the rate of the lag's
moves."""

import sys
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import fem_coupled_friction  # noqa: E402
from fem_coupled_friction import (  # noqa: E402
    NEWTONS,
    coupled_newton,
    coupling_matrix,
    gradient_with_lag_at_u,
    lag_contraction,
    lag_held,
    lagged_then_coupled,
    newton_for,
    phase_iterations,
    reference_merit,
)

from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter, SolverSettings  # noqa: E402
from transtac_sim.physics.box_mesh import box_tet_mesh  # noqa: E402
from transtac_sim.physics.elasticity import EXACT  # noqa: E402
from transtac_sim.physics.host_factorisation import bsr_to_scipy  # noqa: E402
from transtac_sim.physics.newton import NewtonSteps  # noqa: E402


def _pose(x, z):
    P = np.eye(4)
    P[0, 3], P[2, 3] = x, z
    return P


def _pressed_plate(settings: SolverSettings) -> QuasiStaticSolver:
    """A 4 x 4 x 2 mm block under a plate wider than it (friction 0.5), pressed 0.1 mm."""
    V, T = box_tet_mesh(np.linspace(-2, 2, 5), np.linspace(-2, 2, 5), np.linspace(0, 2, 3))
    plate = RigidIndenter.from_trimesh("plate", trimesh.creation.box(extents=(40.0, 40.0, 2.0)), 0.5)
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [plate], settings)
    solver.start([_pose(0.0, 3.0 + 1e-3)])
    solver.solve_frame([_pose(0.0, 2.9)])
    return solver


def test_coupling_term_is_the_gradient_s_derivative_through_the_normal_pressure():
    """A plate wider than the block (every top point in contact, one flat face: n does not change with u, so the term
    is the whole of what the lag leaves out) pressed 0.1 mm and slid 0.2 mm with friction 0.5. At the slid state
    G(u) = gradient with the lag moved to u; (H + J_c) d must match (G(u + h d) - G(u - h d)) / 2h, where H alone
    misses the pressure's share of friction."""
    solver = _pressed_plate(SolverSettings())
    solver.solve_frame([_pose(0.2, 2.9)])
    ind, free = solver._last_ind, solver._linear._free

    def gradient(u: np.ndarray) -> np.ndarray:
        solver.u.dof_values.assign(u.reshape(-1, 3))
        return gradient_with_lag_at_u(solver, ind).numpy().reshape(-1)[free].copy()

    u = solver.u.dof_values.numpy().reshape(-1).copy()
    gradient(u)
    H = bsr_to_scipy(solver._hessian(ind, 1.0, EXACT)).tocsr()[free][:, free]
    J_c = bsr_to_scipy(coupling_matrix(solver, ind)).tocsr()[free][:, free]
    d = np.random.default_rng(0).standard_normal(len(free))
    h = 1e-6 / np.abs(d).max()  # 1e-6 mm: no point crosses the contact or stick-slip boundary
    step = np.zeros_like(u)
    step[free] = h * d
    difference = (gradient(u + step) - gradient(u - step)) / (2.0 * h)
    error_coupled = np.linalg.norm(H @ d + J_c @ d - difference)
    error_symmetric = np.linalg.norm(H @ d - difference)
    assert np.linalg.norm(J_c @ d) > 0.05 * np.linalg.norm(difference)  # the term matters here
    assert error_coupled < 1e-4 * np.linalg.norm(difference), (error_coupled, error_symmetric)
    assert error_symmetric > 100.0 * error_coupled


def _plate_slide(newton=None, linear_solver: str = "auto") -> tuple[np.ndarray, float]:
    """The plate pressed 0.1 mm and slid 0.2 mm with friction 0.5 (the test above), the slide solved by ``newton`` in
    place of the solver's: (the slid displacement (mm), the slide frame's friction_lag_residual_n (N))."""
    solver = _pressed_plate(SolverSettings(friction_lag_moves=1, linear_solver=linear_solver, coarse_cell_mm=1.5))
    if newton is not None:
        solver._newton = lambda ind, may_stall=False, lifting=False: newton(solver, ind, may_stall)
    result = solver.solve_frame([_pose(0.2, 2.9)])
    assert result.record.converged
    return result.displacement_mm, result.record.friction_lag_residual_n


@pytest.mark.parametrize(("method", "linear_solver"), [("gmres", "direct"), ("gmres", "cg"), ("bicgstab", "cg")])
def test_device_coupled_newton_solves_the_lag_s_fixed_point(method, linear_solver):
    """The study's device Newton (``--linear gmres|bicgstab`` on J = H + J_c, preconditioned by block-Jacobi, or with the
    device path's coarse level too where the solver has one, "cg") lands where the host one (LU) does, and leaves the
    lag nothing to move, where the solver with one lag move leaves it a residual far above that."""
    u_lu, residual_lu = _plate_slide(coupled_newton)
    u_krylov, residual_krylov = _plate_slide(NEWTONS[method], linear_solver)
    u_lagged, residual_lagged = _plate_slide()
    # printed on this CPU (GMRES, block-Jacobi): 1.4e-4 mm from LU (its systems solved to a relative 1e-4), lag
    # residuals 4.3e-5 N (GMRES), 5e-13 N (LU), 2.8e-3 N (one lag move, 0.0062 mm from LU)
    np.testing.assert_allclose(u_krylov, u_lu, atol=5e-4)
    assert residual_krylov < 2e-4 and residual_lu < 1e-6, (residual_krylov, residual_lu)
    assert residual_lagged > 10.0 * residual_krylov, (residual_lagged, residual_krylov)
    assert np.abs(u_lagged - u_lu).max() > 10.0 * np.abs(u_krylov - u_lu).max()


def test_lagged_then_coupled_newton_ends_at_the_coupled_solution():
    """``--lagged-first``: the slide solved with friction's first lag never moved, then by the coupled Newton from there,
    ends where the coupled Newton alone does, with the lag converged, and both parts took Newton iterations (the first
    lag is not the solution's: the plate moved)."""
    u_coupled, _ = _plate_slide(coupled_newton)
    phase_iterations.clear()
    u_both, residual_both = _plate_slide(lagged_then_coupled(coupled_newton))
    np.testing.assert_allclose(u_both, u_coupled, atol=1e-6)
    assert residual_both < 1e-6, residual_both
    assert len(phase_iterations) == 1 and all(n >= 1 for n in phase_iterations[0][:2]), phase_iterations


def test_nonmonotone_line_search_compares_with_the_largest_recent_merit_and_ends_at_the_coupled_solution():
    """``--merit-memory``: the reference is the largest of the last M accepted merits (the last one for M = 1), and the
    coupled Newton with it solves the plate slide to the same point as the monotone one, the lag converged."""
    assert reference_merit([3.0, 1.0, 2.0], 1) == 2.0
    assert reference_merit([3.0, 1.0, 2.0], 2) == 2.0
    assert reference_merit([3.0, 1.0, 0.5], 5) == 3.0
    u_monotone, _ = _plate_slide(coupled_newton)
    with mock.patch.object(fem_coupled_friction, "reference_merit", wraps=reference_merit) as spy:
        u_nonmonotone, residual = _plate_slide(newton_for("lu", 5))
    assert spy.call_count >= 1 and all(call.args[1] == 5 for call in spy.call_args_list)
    np.testing.assert_allclose(u_nonmonotone, u_monotone, atol=1e-6)
    assert residual < 1e-6, residual


@pytest.mark.parametrize("n", [40, 300])
def test_lag_contraction_is_the_spectral_radius_of_h_inverse_times_the_coupling(n):
    """Dense (n <= 64) and ARPACK branches against numpy's eigenvalues of H^-1 J_c: H symmetric positive definite and
    sparse, J_c of low rank with the rows and columns of a few "contact" dofs, as friction's coupling is; and 0 for a
    zero J_c."""
    rng = np.random.default_rng(n)
    A = sp.random(n, n, density=0.05, random_state=rng)
    H = (A @ A.T + sp.identity(n) * 2.0).tocsc()
    rows = rng.choice(n, 8, replace=False)  # a row's dof and a column's of the same few "contact points"
    J_c = sp.csr_matrix((rng.standard_normal(8) * 20.0, (rows, np.roll(rows, 1))), shape=(n, n))
    expected = np.max(np.abs(np.linalg.eigvals(np.linalg.solve(H.toarray(), J_c.toarray()))))
    assert expected > 0.1
    np.testing.assert_allclose(lag_contraction(H, J_c), expected, rtol=1e-6)
    assert lag_contraction(H, J_c * 0.0) == 0.0  # nothing in contact: ARPACK would fail on the zero operator


def test_moves_of_friction_s_lag_shrink_its_error_by_the_lag_contraction():
    """``--contraction``'s meaning: on the plate slide (one flat face, so J_c is the lag's whole linearisation), the
    lag's fixed point (solve with the lag held, move it to the solution, solve again) approaches the coupled solution
    by a factor per move that tends to rho(H^-1 J_c) at that solution from below (the dominant mode emerging). Printed
    on this CPU: rho 0.155; |error| ratios 0.118, 0.118, 0.122, 0.124, 0.127, 0.128, 0.129."""
    reference = _pressed_plate(SolverSettings(friction_lag_moves=1, coarse_cell_mm=1.5))
    reference._newton = lambda ind, may_stall=False, lifting=False: coupled_newton(reference, ind, may_stall)
    reference.solve_frame([_pose(0.2, 2.9)])
    u_star = reference.u.dof_values.numpy().reshape(-1).copy()
    solver = _pressed_plate(SolverSettings(friction_lag_moves=1, coarse_cell_mm=1.5))
    errors, rho = [], []

    def lag_fixed_point(ind, may_stall=False, lifting=False):
        for _ in range(8):
            with lag_held(solver):
                result = NewtonSteps._newton(solver, ind, may_stall)
            assert result[0], result
            errors.append(np.linalg.norm(solver.u.dof_values.numpy().reshape(-1) - u_star))
            wp.copy(solver.u_lag.dof_values, solver.u.dof_values)
            solver._update_lag(ind)
        free = solver._linear._free
        H = bsr_to_scipy(solver._hessian(ind, 1.0, EXACT)).tocsr()[free][:, free]
        rho.append(lag_contraction(H, bsr_to_scipy(coupling_matrix(solver, ind)).tocsr()[free][:, free]))
        return result

    solver._newton = lag_fixed_point
    solver.solve_frame([_pose(0.2, 2.9)])
    ratios = np.array(errors[1:]) / np.array(errors[:-1])
    assert 0.05 < rho[0] < 0.5, rho
    assert np.all(ratios < 1.05 * rho[0]) and ratios[-1] > 0.75 * rho[0], (ratios, rho)
    assert np.all(np.diff(ratios[1:]) > 0.0), ratios  # tending to rho from below
