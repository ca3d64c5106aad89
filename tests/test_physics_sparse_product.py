"""The device CG's matrix-vector product (physics/sparse_product.py) against scipy, its projection of the fixed
degrees of freedom (physics/linear.py) against warp.fem's, and its last resort (a shifted system) against scipy's
solve, on a real Newton Hessian; the deviatoric term taken from its constant Hessian (assembly.py) against its
integrals; the volumetric Hessian assembled tet by tet against warp.fem's assembly; the direct path's free-dof
matrix and its kept factorisation's PCG (linear.py)."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh
import warp as wp
import warp.fem as fem
from warp.optim.linear import LinearOperator

from transtac_sim.physics import (
    ElasticMaterial,
    QuasiStaticSolver,
    RigidIndenter,
    SolverSettings,
    contact,
    device_linear,
    elasticity,
    friction_lag,
)
from transtac_sim.physics import linear as linear_module
from transtac_sim.physics.box_mesh import gel_block
from transtac_sim.physics.device_linear import SHIFTS, fixed_blocks, project_fixed
from transtac_sim.physics.host_factorisation import PCG_RATE_CHECK, bsr_to_scipy, pcg
from transtac_sim.physics.linear import LinearSolver
from transtac_sim.physics.reductions import max_abs, negated_free_and_load, step_summary
from transtac_sim.physics.replay import GraphCache
from transtac_sim.physics.sparse_product import block_row_operator
from transtac_sim.physics.volumetric_hessian import VolumetricHessian

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() else [])


def _pressed_solver(degree: int = 2, device: str = "cpu", linear_solver: str = "auto", friction: float = 0.5):
    """A sphere pressed 0.3 mm into a small P2 (or P1) block (friction 0.5 by default) on ``device``, and its indenter
    struct, with the contact state of the solution stored."""
    V, T = gel_block(6.0, 6.0, 2.0, h_fine=0.6, fine_half_width=1.2, growth=2.0)
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=3, radius=2.0), friction)
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [sphere],
                               SolverSettings(degree=degree, linear_solver=linear_solver), device=device)
    P = np.eye(4)
    P[2, 3] = 4.0 + 1e-3
    solver.start([P])
    Q = P.copy()
    Q[2, 3] = 4.0 - 0.3
    solver.solve_frame([Q])
    ind = solver._indenter_struct([Q], [Q])
    solver._gradient(ind)  # stores the contact state the Hessian uses
    return solver, ind


def _launched(solver, evaluate, *args):
    """``evaluate(*args)`` with a graph cache that launches every time, on any device (the reference for a replay)."""
    replaying = solver._graphs
    solver._graphs = GraphCache("cpu")
    try:
        return evaluate(*args)
    finally:
        solver._graphs = replaying


def _next_step(solver):
    """The indenter struct of a load step that presses ``_pressed_solver``'s sphere 0.02 mm further (from its pose)."""
    P = solver.poses[0]
    Q = P.copy()
    Q[2, 3] -= 0.02
    return solver._indenter_struct([Q], [P])


def _pressed_hessian(device: str = "cpu"):
    """The summed Newton Hessian (elastic, barrier where it acts, contact with friction) of ``_pressed_solver``, as
    the device CG receives it."""
    solver, ind = _pressed_solver(device=device)
    return wp.sparse.bsr_copy(solver._hessian(ind, 1.0, True))


@pytest.mark.parametrize("device", DEVICES)  # CUDA: several block rows per thread group, the last one part-filled
def test_block_row_product_matches_scipy(device):
    H = _pressed_hessian(device)
    assert H.nrow % 8 != 0  # a last group of rows that does not fill its thread group
    A = bsr_to_scipy(H)
    assert A.nnz > 0 and abs(A - A.T).max() < 1e-9 * abs(A).max()  # a symmetric Newton matrix with contact terms
    rng = np.random.default_rng(1)
    x, y = rng.standard_normal((2, H.nrow, 3))
    z = wp.zeros(H.nrow, dtype=wp.vec3d, device=device)
    block_row_operator(H).matvec(wp.array(x, dtype=wp.vec3d, device=device), wp.array(y, dtype=wp.vec3d, device=device),
                                 z, 0.7, -1.3)
    expected = 0.7 * (A @ x.reshape(-1)) - 1.3 * y.reshape(-1)
    np.testing.assert_allclose(z.numpy().reshape(-1), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    z2 = wp.array(y, dtype=wp.vec3d, device=device)  # beta = 0 ignores y, and z may be y
    block_row_operator(H).matvec(wp.array(x, dtype=wp.vec3d, device=device), z2, z2, 1.0, 0.0)
    np.testing.assert_allclose(z2.numpy().reshape(-1), A @ x.reshape(-1), rtol=1e-12,
                               atol=1e-12 * np.abs(A @ x.reshape(-1)).max())


@pytest.mark.parametrize("device", DEVICES)
def test_single_precision_product_reads_the_matrix_rounded_to_float32(device):
    """The device CG's product (``single_precision``) equals scipy's product with the blocks rounded to float32 (its
    arithmetic is float64), and differs from the float64 product by no more than that rounding allows."""
    H = _pressed_hessian(device)
    A = bsr_to_scipy(H)
    rounded = A.astype(np.float32).astype(np.float64)
    assert abs(rounded - A).max() > 0.0  # the rounding does change entries
    x = np.random.default_rng(2).standard_normal((H.nrow, 3))
    z = wp.zeros(H.nrow, dtype=wp.vec3d, device=device)
    block_row_operator(H, single_precision=True).matvec(wp.array(x, dtype=wp.vec3d, device=device), z, z, 1.0, 0.0)
    expected = rounded @ x.reshape(-1)
    np.testing.assert_allclose(z.numpy().reshape(-1), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    bound = 2.0 ** -24 * (abs(A) @ np.abs(x.reshape(-1)))  # each entry within 2^-24 of itself
    assert np.all(np.abs(z.numpy().reshape(-1) - A @ x.reshape(-1)) <= bound * (1 + 1e-9) + 1e-15)


def test_fixed_projection_matches_warp_fem():
    """(I - P) H (I - P) + P in place, block by block, equals warp.fem.project_linear_system's sparse products."""
    H = _pressed_hessian()
    fixed = np.random.default_rng(0).random((H.nrow, 3)) < 0.2  # components fixed at random, some nodes partly
    blocks = np.zeros((H.nrow, 3, 3))
    blocks[:, [0, 1, 2], [0, 1, 2]] = fixed
    by_fem = wp.sparse.bsr_copy(H)
    fem.project_linear_system(by_fem, wp.zeros(H.nrow, dtype=wp.vec3d), wp.sparse.bsr_diag(wp.array(blocks, dtype=wp.mat33d)),
                              normalize_projector=False)
    project_fixed(H, wp.array(fixed.astype(np.float64), dtype=wp.vec3d), fixed_blocks(H, fixed))
    A, B = bsr_to_scipy(by_fem), bsr_to_scipy(H)
    assert abs(A - B).max() <= 1e-14 * abs(A).max() and abs(A - bsr_to_scipy(_pressed_hessian())).max() > 0.0


@fem.integrand
def _volumetric_hessian_reference(s: fem.Sample, du: fem.Field, v: fem.Field, u: fem.Field,
                                  params: wp.array(dtype=wp.vec2d), geometric: wp.float64, clamp: int,
                                  barrier_tets: wp.array(dtype=wp.int32)):
    """The volumetric Hessian's integrand as elasticity.py states it, for warp.fem's generic assembly."""
    F = elasticity.deformation_gradient(fem.grad(u, s))
    mu = params[s.element_index][0]
    lam = params[s.element_index][1]
    p = lam * (wp.determinant(F) - wp.float64(1.0) - mu / lam)
    if clamp != 0:
        bound = elasticity.pressure_bound(F, mu)
        if barrier_tets[s.element_index] != 0:
            bound = wp.float64(0.5) * bound
        p = wp.clamp(p, -bound, bound)
    cof = elasticity.cofactor(F)
    gdu = fem.grad(du, s)
    gv = fem.grad(v, s)
    return lam * wp.ddot(cof, gdu) * wp.ddot(cof, gv) + geometric * p * wp.ddot(elasticity.cofactor_delta(F, gdu), gv)


def _volumetric_reference(solver, geometric: float, clamp: bool) -> sp.csr_matrix:
    return bsr_to_scipy(fem.integrate(
        _volumetric_hessian_reference, quadrature=solver._q_vol, fields={"du": solver._trial, "v": solver._test,
                                                                         "u": solver.u},
        values={"params": solver._params, "geometric": geometric, "clamp": int(clamp),
                "barrier_tets": solver._barrier_tets}, output_dtype=wp.float64))


def test_summed_hessian_equals_the_sum_of_its_parts():
    """hessian_assembly.py adds each Hessian part into one kept matrix: the volumetric part tet by tet, the others
    through precomputed block places. The result equals scipy's sum of the parts (deviatoric, volumetric by warp.fem's
    generic assembly, contact with friction), and a second assembly overwrites the first instead of adding to it."""
    solver, ind = _pressed_solver()
    first = bsr_to_scipy(solver._hessian(ind, 1.0, False))
    H = bsr_to_scipy(solver._hessian(ind, 1.0, False))
    parts = [bsr_to_scipy(solver._deviatoric().H), _volumetric_reference(solver, 1.0, False)]
    parts += [bsr_to_scipy(M) for M in solver._H_parts.values()]
    assert set(solver._H_parts) >= {"contact"} and bsr_to_scipy(solver._H_parts["contact"]).nnz > 0
    expected = sum(parts[1:], parts[0])
    assert abs(H - expected).max() <= 1e-13 * abs(expected).max()
    assert abs(first - H).max() <= 1e-13 * abs(expected).max()  # not accumulated over the two calls


def test_device_last_resort_solves_the_shifted_system():
    """Newton's last Hessian (Gauss-Newton, ``definite=False``) that the device CG does not solve (here: 8 iterations
    allowed, to a relative residual of 1e-10) is solved with a Levenberg-Marquardt shift, H + lambda |diag H|
    (device_linear.py ``SHIFTS``): the step equals scipy's solution of that shifted system on the free dofs and is a
    descent direction. A Hessian that must be positive definite returns None instead, and so does the last one where
    no shift converges (1 iteration allowed); nothing is handed to the host."""
    solver, ind = _pressed_solver()
    linear = LinearSolver("cg", solver._fixed_nodes, solver.device)
    linear.cg_maxiter = 8
    g = solver._gradient(ind).numpy().copy()  # (the kept gradient: the next call overwrites it)
    g[solver._fixed_nodes] = 0.0
    rhs = wp.array(-g, dtype=wp.vec3d)
    H = solver._hessian(ind, 0.0, True)
    projected = wp.sparse.bsr_copy(H)
    project_fixed(projected, linear._fixed, fixed_blocks(projected, solver._fixed_nodes))
    A = bsr_to_scipy(projected).tocsr()[linear._free][:, linear._free]
    du = linear.solve(H, rhs, definite=False, rtol=1e-10)
    assert du is not None and linear.shifted_solves == 1 and linear.last_shift in SHIFTS
    shifted = (A + linear.last_shift * sp.diags(np.abs(A.diagonal()))).tocsc()
    expected = spla.spsolve(shifted, -g.reshape(-1)[linear._free])
    x = du.numpy().reshape(-1)
    np.testing.assert_allclose(x[linear._free], expected, rtol=0, atol=1e-7 * np.abs(expected).max())
    assert np.all(x[~np.isin(np.arange(x.size), linear._free)] == 0.0) and float(np.dot(x, -g.reshape(-1))) > 0.0
    assert linear.solve(solver._hessian(ind, 0.0, True), rhs, definite=True, rtol=1e-10) is None
    linear.cg_maxiter = 1
    assert linear.solve(solver._hessian(ind, 0.0, True), rhs, definite=False, rtol=1e-10) is None


def test_device_last_resort_tries_the_float64_product_before_a_shift(monkeypatch):
    """Where the device CG's float32 product finds Newton's last Hessian (``definite=False``) not positive definite, the
    system is solved again with the float64 product before any Levenberg-Marquardt shift: near inverted elements the
    barrier's blocks dwarf the rest, and their float32 rounding can make a positive definite Gauss-Newton Hessian look
    indefinite (train_random sequence 72, BENCHMARKS.md ``fem_float64_fallback_gpu``). Here the float32 product is
    replaced by one of -H (refused at its first direction): the step is the unshifted solution of H, counted in
    ``float64_solves``; a Hessian that must be positive definite is still refused without that second solve."""
    made = device_linear.block_row_operator

    def negated_when_rounded(H, single_precision=False, rounded=None, round_now=True):
        op = made(H, single_precision, rounded, round_now)
        if not single_precision:
            return op
        negated = LinearOperator(op.shape, op.dtype, op.device,
                                 lambda x, y, z, alpha, beta: op.matvec(x, y, z, -alpha, beta))
        negated.graph_key = None
        return negated

    monkeypatch.setattr(device_linear, "block_row_operator", negated_when_rounded)
    solver, ind = _pressed_solver()
    linear = LinearSolver("cg", solver._fixed_nodes, solver.device)
    g = solver._gradient(ind).numpy().copy()  # (the kept gradient: the next call overwrites it)
    g[solver._fixed_nodes] = 0.0
    rhs = wp.array(-g, dtype=wp.vec3d)
    assert linear.solve(solver._hessian(ind, 0.0, True), rhs, definite=True, rtol=1e-10) is None
    assert linear.float64_solves == 0 and linear.not_definite == 1
    H = solver._hessian(ind, 0.0, True)
    du = linear.solve(H, rhs, definite=False, rtol=1e-10)
    assert du is not None and linear.float64_solves == 1 and linear.shifted_solves == 0 and linear.last_shift == 0.0
    A = bsr_to_scipy(H).tocsr()[linear._free][:, linear._free]  # H was projected in place by the solve
    expected = spla.spsolve(A.tocsc(), -g.reshape(-1)[linear._free])
    np.testing.assert_allclose(du.numpy().reshape(-1)[linear._free], expected, rtol=0,
                               atol=1e-7 * np.abs(expected).max())


@pytest.mark.skipif("cuda:0" not in DEVICES, reason="the GPU's Newton path (reads folded into one) needs a GPU")
def test_gpu_newton_with_the_device_cg_ends_where_the_host_factorisation_does():
    """The sphere pressed 0.3 mm without friction (``_pressed_solver``; with it the two would follow friction's lag by
    different paths), then 0.05 mm more, on a GPU, whose Newton folds its scalars into one read per pass (the barrier's
    energy, the contact sides' coverage and E with |g|; with the device CG the step's slope and length come from the
    CG's state): with the device CG it ends where it does with the host factorisation, whose steps are exact (the same
    displacement within 2e-4 mm, the same contact force within 0.1 %). (The GPU machine builds no CPU kernels, so the
    CPU path is not the reference here.)"""
    cg, _ = _pressed_solver(device="cuda:0", friction=0.0)
    host, _ = _pressed_solver(device="cuda:0", linear_solver="direct", friction=0.0)
    P = cg.poses[0].copy()
    P[2, 3] -= 0.05  # a second frame, from each one's own first one
    r_cg, r_host = cg.solve_frame([P]), host.solve_frame([P])
    assert r_cg.record.converged and r_host.record.converged
    assert np.abs(r_cg.displacement_mm - r_host.displacement_mm).max() <= 2e-4  # mm, of about 0.35 mm
    assert np.abs(r_cg.forces_n - r_host.forces_n).max() <= 1e-3 * np.abs(r_host.forces_n).max()


@pytest.mark.parametrize("device", DEVICES)
def test_newtons_one_read_gives_what_separate_reads_give(device):
    """Newton's pass reads its scalars together (newton.py ``_read_gradient``): -g, |g|, the support's load, friction's
    lag distance, and on a GPU E(u), equal to what the separate evaluations give; the barrier's energy and, on a GPU,
    the contact sides' coverage flag are kept for the Hessian without a read of their own."""
    solver, ind = _pressed_solver(device=device)
    u = solver.u.dof_values.numpy()
    solver.u_lag.dof_values.assign(wp.array(0.9 * u, dtype=wp.vec3d, device=device))  # a lag 10 % behind
    rhs, g_norm, load, change, energy = solver._read_gradient(ind, True, True)
    assert solver._barrier_energy == float(solver._barrier_sum.numpy()[0])
    if solver.device.is_cuda:
        assert solver._contact_stale is bool(solver._contact_sides.stale.numpy()[0] > 0.0)
        assert energy == pytest.approx(solver._energy(solver.u, ind), rel=1e-13)
    else:
        assert solver._contact_stale is None and energy is None  # the CPU reads those where it needs them
    assert change == max_abs(solver.u.dof_values, solver.u_lag.dof_values) > 0.0
    expected = negated_free_and_load(solver._gradient(ind), solver._fixed_mask)
    assert (g_norm, load) == expected[1:] and np.array_equal(rhs.numpy(), expected[0].numpy())
    assert solver._read_gradient(ind, False, False)[3:] == (None, None)


@pytest.mark.parametrize("device", DEVICES)
def test_device_solutions_come_with_their_summary(device):
    """The device path's solution of a Newton system and its step estimate come with (x . b, max |x|, finite) read with
    the CG's state (``LinearSolver.known_summary``), equal to what reductions.py reduces from them; another array, and
    the host path, have none (the caller reduces)."""
    solver, ind = _pressed_solver(device=device)
    linear = LinearSolver("cg", solver._fixed_nodes, solver.device)
    g = solver._gradient(ind).numpy().copy()  # (the kept gradient: the next call overwrites it)
    g[solver._fixed_nodes] = 0.0
    rhs = wp.array(-g, dtype=wp.vec3d, device=device)
    du = linear.solve(solver._hessian(ind, 1.0, True), rhs, rtol=0.01)
    dot, largest, finite = linear.known_summary(du)
    expected = step_summary(du, rhs)
    assert finite and expected[2] and dot == pytest.approx(expected[0], rel=1e-12) and largest == expected[1] > 0.0
    estimate = linear.solve_last(wp.array(0.5 * -g, dtype=wp.vec3d, device=device))
    assert linear.known_summary(estimate)[1] == max_abs(estimate) > 0.0 and linear.known_summary(du) is None
    assert linear.known_summary(wp.clone(estimate)) is None
    host = LinearSolver("direct", solver._fixed_nodes, solver.device)
    assert host.known_summary(host.solve(solver._hessian(ind, 1.0, True), rhs)) is None


@pytest.mark.parametrize("method", ["cg", "direct"])
def test_a_solve_is_refined_to_the_caller_s_tight_tolerance(monkeypatch, method):
    """``LinearSolver.solve(..., tight=T)``: a solution below ``exact_below`` is refined to T instead of cg_tol, on
    both paths (Newton's floor where the force test is on, convergence_tests.py ``_force_forcing``): the device CG's
    second stage, and the direct path's PCG with the factorisation kept from a first system, are asked for T, and
    the solution's relative residual is within it; by default they are asked for cg_tol."""
    solver, ind = _pressed_solver()
    asked = []
    if method == "cg":
        cg = device_linear.definite_cg

        def noting(A, b, x, rtol, *args, **kwargs):
            asked.append(rtol)
            return cg(A, b, x, rtol, *args, **kwargs)

        monkeypatch.setattr(device_linear, "definite_cg", noting)
    else:
        pcg_ = linear_module.pcg

        def noting(A, b, M, rtol, *args, **kwargs):
            asked.append(rtol)
            return pcg_(A, b, M, rtol, *args, **kwargs)

        monkeypatch.setattr(linear_module, "pcg", noting)
    g = solver._gradient(ind).numpy().copy()  # (the kept gradient: the next call overwrites it)
    g[solver._fixed_nodes] = 0.0
    rhs = wp.array(-g, dtype=wp.vec3d)

    def solved(tight):
        linear = LinearSolver(method, solver._fixed_nodes, solver.device)
        if method == "direct":  # factorised here; the next system (Gauss-Newton's) is solved by PCG with it
            linear.solve(solver._hessian(ind, 1.0, True), rhs)
        asked.clear()
        H = solver._hessian(ind, 1.0 if method == "cg" else 0.0, True)
        x = linear.solve(H, rhs, rtol=0.3, exact_below=1e9, tight=tight)
        A = bsr_to_scipy(H).tocsr()[linear._free][:, linear._free]
        b = -g.reshape(-1)[linear._free]
        return list(asked), np.linalg.norm(b - A @ x.numpy().reshape(-1)[linear._free]) / np.linalg.norm(b), linear

    asked_loose, residual, linear = solved(0.05)
    assert asked_loose == [0.3, 0.05] and residual <= 0.05
    asked_default, residual, _ = solved(None)
    # (1.01: the float32 product's round-off)
    assert asked_default == [0.3, linear.cg_tol] and residual <= 1.01 * linear.cg_tol


@pytest.mark.parametrize("device", DEVICES)
def test_device_step_estimate_solves_to_its_tolerance_within_its_cap(monkeypatch, device):
    """The device's step estimate (``solve_last``, device_linear.py): the last converged system solved for a new
    right-hand side to ``ESTIMATE_RTOL``, on to ``cg_tol`` where its max |x| is within [``refine_above``,
    ``exact_below``); within ``ESTIMATE_CAP_FACTOR`` times that system's CG iterations, else None; its iterations and
    failures counted."""
    solver, ind = _pressed_solver(device=device)
    linear = LinearSolver("cg", solver._fixed_nodes, solver.device)
    g = solver._gradient(ind).numpy().copy()  # (the kept gradient: the next call overwrites it)
    g[solver._fixed_nodes] = 0.0
    H = solver._hessian(ind, 1.0, True)
    assert linear.solve(H, wp.array(-g, dtype=wp.vec3d, device=device), rtol=0.01) is not None
    A = bsr_to_scipy(H).tocsr()[linear._free][:, linear._free]  # H was projected in place by the solve
    b = np.random.default_rng(7).standard_normal(g.shape)
    b[solver._fixed_nodes] = 0.0

    def residual(x):
        return np.linalg.norm(b.reshape(-1)[linear._free] - A @ x.numpy().reshape(-1)[linear._free]) / np.linalg.norm(b)

    loose = linear.solve_last(wp.array(b, dtype=wp.vec3d, device=device))
    assert loose is not None and linear.cg_tol < residual(loose) <= device_linear.ESTIMATE_RTOL
    assert np.all(loose.numpy()[solver._fixed_nodes] == 0.0) and linear.estimate_iterations > 0
    tight = linear.solve_last(wp.array(b, dtype=wp.vec3d, device=device), exact_below=1e9)  # small enough: on to cg_tol
    assert residual(tight) <= linear.cg_tol
    length = float(np.abs(loose.numpy()).max())  # below the band [refine_above, exact_below): the loose one is kept
    kept = linear.solve_last(wp.array(b, dtype=wp.vec3d, device=device), exact_below=1e9, refine_above=2.0 * length)
    assert linear.cg_tol < residual(kept) <= device_linear.ESTIMATE_RTOL
    # the premise of friction_lag.ESTIMATE_REFINE_BAND (low, high): a loose length below low x newton_tol_mm refines to
    # below newton_tol_mm and one above high x newton_tol_mm to above it (the convergence test decides as the refined
    # would)
    low, high = friction_lag.ESTIMATE_REFINE_BAND
    assert 1.0 / high < float(np.abs(tight.numpy()).max()) / length < 1.0 / low
    monkeypatch.setattr(device_linear, "ESTIMATE_RTOL", 1e-12)  # not reachable within 2x the system's iterations
    assert linear.solve_last(wp.array(b, dtype=wp.vec3d, device=device)) is None and linear.estimates_unconverged == 1


@pytest.mark.parametrize("device", DEVICES)
def test_replayed_energy_and_min_det_read_the_current_values(device):
    """``_energy`` and ``_min_det`` replay CUDA graphs (replay.py): a replay reads the field's current values, the
    contact state changed in place (friction's lag moved) and a new load step's poses (written into the solver's one
    indenter struct), a stiffness change makes a new graph, and every value equals the one launched without a graph.
    On the CPU there are no graphs: its case checks the launch path only; the replay is checked by the CUDA case."""
    solver, ind = _pressed_solver(device=device)
    u0 = solver.u.dof_values.numpy()

    def launched(u, which):  # without any graph
        solver._energy_terms(u, which)
        J = wp.empty(solver._q_det.total_point_count(), dtype=wp.float64, device=solver.device)
        fem.interpolate(elasticity.det_form, dest=J, at=solver._q_det, fields={"u": u})
        return float(solver._energy_sum.numpy()[0]), float(J.numpy().min())

    solver._graphs.clear()  # the graphs of the solve that made the state
    before = solver._graphs.captures
    expected, got = [], []
    for k, stiffness in enumerate((ind.stiffness, 2.0 * ind.stiffness)):  # baked into the energy's graph: a new key
        ind.stiffness = stiffness
        for scale in (1.0, 0.5, 0.9, 0.8):  # the first call launches, the second captures, the rest replay
            solver._u_try.dof_values.assign((scale + 0.05 * k) * u0)
            got.append((solver._energy(solver._u_try, ind), solver._min_det(solver._u_try)))
            expected.append(launched(solver._u_try, ind))
    solver.u_lag.dof_values.assign(0.5 * u0)  # friction's lag moved: the contact state changes in place
    solver._update_lag(ind)
    got.append((solver._energy(solver._u_try, ind), solver._min_det(solver._u_try)))  # replayed
    expected.append(launched(solver._u_try, ind))
    ind.stiffness = solver.contact_stiffness  # the first stiffness again: replayed
    got.append((solver._energy(solver._u_try, ind), solver._min_det(solver._u_try)))
    expected.append(launched(solver._u_try, ind))
    captured = solver._graphs.captures
    step = _next_step(solver)  # the next load step: its poses written into the same struct
    assert step is ind
    for _ in range(2):
        got.append((solver._energy(solver._u_try, step), solver._min_det(solver._u_try)))  # replayed
        expected.append(launched(solver._u_try, step))
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    assert len({e for e, _ in got[:8]}) == 8  # every state gave its own energy
    assert got[8][0] != got[7][0]  # the moved lag changed the friction energy, and the replay saw it
    assert got[10][0] != got[9][0]  # so did the indenter's new pose
    if solver.device.is_cuda:  # energy and det F once each, the energy again for the new stiffness; not the new poses
        assert solver._graphs.captures - before == 3 and solver._graphs.captures == captured


@pytest.mark.parametrize("device", DEVICES)
def test_replayed_gradient_and_hessian_read_the_current_values(device):
    """``_gradient`` and ``_hessian`` replay CUDA graphs (replay.py): a replay reads the field's current values, the
    contact state its gradient stores, friction's lag moved in place and a new load step's poses; a stiffness change
    makes new graphs; the gradient, the barrier flag and both Hessians (exact and clamped) equal those launched without
    a graph (the same methods with a graph cache that only launches). The CPU case checks the launch path only."""
    solver, ind = _pressed_solver(device=device)
    u0 = solver.u.dof_values.numpy().copy()
    replaying = solver._graphs

    def evaluate(which):  # the gradient, the barrier flag, the exact and the clamped Hessians' blocks
        g = solver._gradient(which).numpy().copy()
        acts = solver._barrier_acts
        H = [solver._hessian(which, 1.0, clamp).values.numpy()[:solver._H.nnz].copy() for clamp in (0, 1)]
        return g, acts, H

    replaying.clear()
    before = replaying.captures
    states = [(k, scale) for k in (1.0, 2.0) for scale in (1.0, 0.5, 0.9, 0.8)]  # launch, capture, then replays
    got, expected = [], []
    stiffness = ind.stiffness
    for k, scale in states:
        ind.stiffness = k * stiffness  # baked into the graphs: a new key
        solver.u.dof_values.assign(scale * u0)
        got.append(evaluate(ind))
        expected.append(_launched(solver, evaluate, ind))
    solver.u_lag.dof_values.assign(0.5 * u0)  # friction's lag moved: the contact state changes in place
    solver._update_lag(ind)
    got.append(evaluate(ind))
    expected.append(_launched(solver, evaluate, ind))
    ind.stiffness = stiffness
    got.append(evaluate(ind))  # the first stiffness's graphs again
    expected.append(_launched(solver, evaluate, ind))
    captured = replaying.captures
    step = _next_step(solver)  # the next load step's poses, in the same struct
    for _ in range(2):
        got.append(evaluate(step))
        expected.append(_launched(solver, evaluate, step))
    for (g, acts, H), (g_ref, acts_ref, H_ref) in zip(got, expected, strict=True):
        np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-12 * np.abs(g_ref).max())
        assert acts == acts_ref
        for A, A_ref in zip(H, H_ref, strict=True):
            np.testing.assert_allclose(A, A_ref, rtol=0, atol=1e-12 * np.abs(A_ref).max())
    norms = [float(np.abs(g).sum()) for g, _, _ in got]
    assert len(set(norms[:8])) == 8 and norms[8] != norms[7]  # every state, and the moved lag, changed the gradient
    assert norms[10] != norms[9]  # so did the new pose
    assert not np.array_equal(got[0][2][0], got[0][2][1])  # the clamp acts somewhere: two Hessians
    if solver.device.is_cuda:  # the gradient and both Hessians for each stiffness; none for the new poses
        assert replaying.captures - before >= 6 and replaying.captures == captured


@fem.integrand
def _deviatoric_energy_reference(s: fem.Sample, u: fem.Field, params: wp.array(dtype=wp.vec2d)):
    """The deviatoric energy's integrand as elasticity.py states it: mu/2 (|F|^2 - 3)."""
    F = elasticity.deformation_gradient(fem.grad(u, s))
    return wp.float64(0.5) * params[s.element_index][0] * (wp.ddot(F, F) - wp.float64(3.0))


def test_deviatoric_energy_and_gradient_are_its_quadratic_form():
    """assembly.py takes the deviatoric term's energy and gradient from its constant Hessian, c . u + u . H_dev u / 2
    and c + H_dev u: they equal the term's integrals (order 2, exact for P2) at a displacement with contact."""
    solver, _ = _pressed_solver()
    u = solver.u.dof_values.numpy()
    assert np.abs(u).max() > 0.1  # the pressed state
    dev = solver._deviatoric()
    H, c = bsr_to_scipy(dev.H), dev.c.numpy().reshape(-1)
    vals = {"params": solver._params}
    energy = fem.integrate(_deviatoric_energy_reference, quadrature=solver._q_dev, fields={"u": solver.u},
                           values=vals)
    gradient = fem.integrate(elasticity.deviatoric_gradient_form, quadrature=solver._q_dev,
                             fields={"u": solver.u, "v": solver._test}, values=vals, output_dtype=wp.vec3d).numpy()
    x = u.reshape(-1)
    np.testing.assert_allclose(c @ x + 0.5 * x @ (H @ x), energy, rtol=1e-12)
    np.testing.assert_allclose(c + H @ x, gradient.reshape(-1), rtol=0, atol=1e-12 * np.abs(gradient).max())


def test_free_matrix_gathers_each_new_hessian():
    """The direct path's free-dof matrix (linear.py ``_free_matrix``: a gather map made on the first matrix) equals
    scipy's slicing of each Hessian, also of one assembled later with other values."""
    solver, ind = _pressed_solver()
    linear = LinearSolver("direct", solver._fixed_nodes, solver.device)
    for geometric in (1.0, 0.0):
        H = solver._hessian(ind, geometric, False)
        expected = bsr_to_scipy(H).tocsr()[linear._free][:, linear._free]
        A = linear._free_matrix(H)
        assert A.shape == expected.shape and abs(A - expected).max() == 0.0


def test_kept_factorisation_pcg_gives_up_early_where_it_would_not_converge():
    """``pcg`` with a poor preconditioner (the factorisation of another matrix) stops before its cap where its rate
    so far cannot reach the tolerance in time, converges with a good one, and does nothing from a solution."""
    rng = np.random.default_rng(0)
    n = 400
    L = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(n, n)).tocsc()
    A = (L + sp.diags(rng.uniform(0.01, 100.0, n))).tocsc()  # badly scaled: L's factor is a poor preconditioner
    b = rng.standard_normal(n)
    x, iterations = pcg(A, b, spla.factorized(L.tocsc()), 1e-6, 20)
    assert x is None and PCG_RATE_CHECK <= iterations < 20
    x, iterations = pcg(A, b, spla.factorized(A), 1e-6, 20)
    assert x is not None and iterations <= 2 and np.linalg.norm(A @ x - b) <= 1e-6 * np.linalg.norm(b)
    x_again, iterations = pcg(A, b, spla.factorized(L.tocsc()), 1e-6, 20, x0=x)
    assert iterations == 0 and np.array_equal(x_again, x)  # started at a solution: nothing to do
    x_negative, iterations = pcg((-A).tocsc(), -b, spla.factorized(A), 1e-6, 20, x0=-x)
    assert x_negative is None and iterations == 0  # a solution, but of a matrix that is not positive definite along it


def test_direct_path_solves_to_the_forcing_term_with_its_kept_factorisation():
    """The direct path's Newton systems after the first are solved by PCG with the kept factorisation to Newton's
    relative tolerance (linear.py ``_solve_free``), on to ``cg_tol`` where the solution is below ``exact_below``, and
    from ``guess`` where one is given; a new factorisation solves exactly."""
    solver, ind = _pressed_solver()
    linear = LinearSolver("direct", solver._fixed_nodes, solver.device)
    g = solver._gradient(ind).numpy().copy()  # (the kept gradient: the next call overwrites it)
    g[solver._fixed_nodes] = 0.0
    rhs = wp.array(-g, dtype=wp.vec3d)

    def residual(H, du):  # |b - A x| / |b| on the free dofs
        A = linear._free_matrix(H)
        b = -g.reshape(-1)[linear._free]
        return np.linalg.norm(b - A @ du.numpy().reshape(-1)[linear._free]) / np.linalg.norm(b)

    H = solver._hessian(ind, 1.0, True)  # the clamped Hessian: positive definite
    first = linear.solve(H, rhs, rtol=0.05)
    assert linear.factorisations == 1 and residual(H, first) < 1e-10  # factorised: exact whatever the tolerance
    H = solver._hessian(ind, 1.0, False)  # the exact Hessian: the kept factorisation is another matrix's
    loose = linear.solve(H, rhs, rtol=0.05)
    assert linear.factorisations == 1 and 1e-4 < residual(H, loose) <= 0.05
    tight = linear.solve(solver._hessian(ind, 1.0, False), rhs, rtol=0.05, exact_below=1e3)
    assert linear.factorisations == 1 and residual(H, tight) <= linear.cg_tol
    iterations = linear.last_iterations
    again = linear.solve(solver._hessian(ind, 1.0, False), rhs, rtol=0.05, guess=tight)
    assert linear.last_iterations == 0 and np.array_equal(again.numpy(), tight.numpy()) and iterations > 0


def test_direct_path_step_estimate_is_refined_only_within_its_band(monkeypatch):
    """The direct path's step estimate (``solve_last``): PCG with the kept factorisation to its loose tolerance, then on
    to the one asked for only where the loose solution's max |x| lies within [``refine_above``, ``exact_below``)."""
    solver, ind = _pressed_solver()
    linear = LinearSolver("direct", solver._fixed_nodes, solver.device)
    g = solver._gradient(ind).numpy().copy()
    g[solver._fixed_nodes] = 0.0
    rhs = wp.array(-g, dtype=wp.vec3d)
    assert linear.solve(solver._hessian(ind, 1.0, True), rhs) is not None  # factorised: kept for the estimates
    tolerances = []

    def recording_pcg(A, b, M, rtol, maxiter, x0=None):
        tolerances.append(rtol)
        return pcg(A, b, M, rtol, maxiter, x0)

    monkeypatch.setattr(linear_module, "pcg", recording_pcg)
    length = float(np.abs(linear.solve_last(rhs, rtol=1e-8).numpy()).max())  # no band given: loose only
    assert tolerances == [linear_module.ESTIMATE_RTOL] and length > 0.0
    tolerances.clear()
    linear.solve_last(rhs, rtol=1e-8, exact_below=2.0 * length, refine_above=0.5 * length)  # within: refined
    assert tolerances == [linear_module.ESTIMATE_RTOL, 1e-8]
    tolerances.clear()
    linear.solve_last(rhs, rtol=1e-8, exact_below=4.0 * length, refine_above=2.0 * length)  # shorter than the band
    assert tolerances == [linear_module.ESTIMATE_RTOL]


def test_step_estimate_band_is_about_the_threshold_it_is_compared_with():
    """``_estimate_band`` (friction_lag.py): ``ESTIMATE_REFINE_BAND`` = (0.25, 2) x newton_tol_mm where friction's lag
    may not move (no change given, or one below 10 newton_tol_mm); where it may, x the lag's threshold (``_move_lag``:
    max(tol, r |u - u_lag|), r = 0.1 on the direct path), capped at ``ESTIMATE_REFINED_BELOW`` = 10 newton_tol_mm, and
    empty where the band lies above that."""
    assert friction_lag.ESTIMATE_REFINE_BAND == (0.25, 2.0) and friction_lag.ESTIMATE_REFINED_BELOW == 10.0
    solver, _ = _pressed_solver()
    tol = solver.settings.newton_tol_mm

    def band(change):  # (refine_above, exact_below) in newton_tol_mm
        b = solver._estimate_band(None if change is None else change * tol)
        return round(b["refine_above"] / tol, 9), round(b["exact_below"] / tol, 9)

    assert band(None) == band(5.0) == (0.25, 2.0)  # the convergence test's
    assert band(20.0) == (0.5, 4.0)  # lag threshold 2 tol
    assert band(80.0) == (2.0, 10.0)  # threshold 8 tol: 16 capped at 10
    assert band(200.0) == (5.0, 10.0)  # threshold 20 tol
    low, high = band(1000.0)  # threshold 100 tol: nothing below 10 tol to refine
    assert low >= high


def test_newton_passes_its_refinement_band_to_the_step_estimate(monkeypatch):
    """Newton asks for each step estimate with its band (``_estimate_band``): about newton_tol_mm once friction's lag may
    no longer move, about the lag's threshold before, never above ``ESTIMATE_REFINED_BELOW`` x newton_tol_mm."""
    solver, _ = _pressed_solver()
    asked = []
    solve_last = solver._linear.solve_last

    def recording(rhs, **kwargs):
        asked.append(kwargs)
        return solve_last(rhs, **kwargs)

    monkeypatch.setattr(solver._linear, "solve_last", recording)
    Q = solver.poses[0].copy()
    Q[2, 3] -= 0.05
    solver.solve_frame([Q])
    tol = solver.settings.newton_tol_mm
    low, high = friction_lag.ESTIMATE_REFINE_BAND
    assert asked and all(kw.keys() == {"exact_below", "refine_above"} for kw in asked)
    convergence = {"refine_above": low * tol, "exact_below": high * tol}  # where the lag may not move
    assert any(kw == pytest.approx(convergence) for kw in asked)
    assert any(kw["refine_above"] > low * tol * (1 + 1e-9) for kw in asked)  # about a lag threshold (friction 0.5)
    assert all(kw["exact_below"] <= friction_lag.ESTIMATE_REFINED_BELOW * tol * (1 + 1e-12) for kw in asked)


def test_contact_outside_the_indenters_box_makes_no_query():
    """contact.py skips the mesh query where a point lies outside the indenter's local bounding box: the contact
    energy, gradient and largest penetration equal those with a box that contains every point (the query everywhere)."""
    solver, ind = _pressed_solver()
    everywhere = solver._indenter_struct([solver.poses[0]], [solver.poses[0]], role="everywhere")  # another struct
    everywhere.box_lo = wp.array([[-1e9, -1e9, -1e9]], dtype=wp.vec3d)
    everywhere.box_hi = wp.array([[1e9, 1e9, 1e9]], dtype=wp.vec3d)
    lo, hi = ind.box_lo.numpy()[0], ind.box_hi.numpy()[0]
    assert np.all(hi - lo < 4.1) and np.all(hi - lo > 3.9)  # the 2 mm sphere's box
    pen = solver._max_penetration(ind)
    assert pen > 0.0 and pen == solver._max_penetration(everywhere)
    assert solver._energy(solver.u, ind) == solver._energy(solver.u, everywhere)
    np.testing.assert_array_equal(solver._gradient(ind).numpy().copy(), solver._gradient(everywhere).numpy())


@pytest.mark.parametrize("device", DEVICES)  # the GPU writes a block per thread, the CPU a tet's blocks per thread
@pytest.mark.parametrize("degree", [1, 2])
def test_volumetric_hessian_tet_by_tet_equals_warp_fems_assembly(degree, device):
    """volumetric_hessian.py's blocks (only the nodes whose basis gradient at the centroid is not zero) equal warp.fem's
    assembly of the integrand over all node pairs: exact, clamped (with the barrier's halved bound in some tets) and
    Gauss-Newton, on a pressed P1 and P2 block."""
    solver, ind = _pressed_solver(degree, device=device)
    rng = np.random.default_rng(2)
    solver._barrier_tets.assign(wp.array((rng.random(len(solver.tets)) < 0.3).astype(np.int32), dtype=wp.int32,
                                         device=device))
    total = wp.sparse.bsr_copy(solver._deviatoric().H)
    volumetric = VolumetricHessian.make(solver._tets(), total, solver.device)
    clamped = 0
    for geometric, clamp in ((1.0, False), (1.0, True), (0.0, True)):
        total.values.zero_()
        volumetric.add_to(total, solver.u.dof_values, solver._params, geometric, clamp, solver._barrier_tets)
        expected = _volumetric_reference(solver, geometric, clamp)
        A = bsr_to_scipy(total)
        assert abs(A - expected).max() <= 1e-12 * abs(expected).max()
        clamped += clamp and geometric > 0.0 and abs(expected - _volumetric_reference(solver, 1.0, False)).max() > 0.0
    assert clamped == 1  # the clamp acts somewhere in this state


def test_contact_hessian_over_its_sides_equals_the_full_assembly():
    """The contact Hessian integrated over the sides where it can be non-zero (contact_sides.py) equals warp.fem's
    assembly over every touchable side, and that subset is a small part of them."""
    solver, ind = _pressed_solver()
    solver._hessian(ind, 1.0)
    subset_hessian = bsr_to_scipy(solver._H_parts["contact"])
    subset = solver._contact_sides.current
    sides = subset.mask.size
    assert 0 < np.count_nonzero(subset.mask) < sides / 4
    full = fem.integrate(contact.contact_hessian_form, quadrature=solver._q_contact,
                         fields={"du": fem.make_trial(solver._space, domain=solver._sides), "v": solver._side_test},
                         values=solver._contact_values(ind) | {"qp_base": wp.array(np.arange(sides) * subset.points,
                                                                                     dtype=int),
                                                             "points": subset.points}, output_dtype=wp.float64)
    expected = bsr_to_scipy(full)
    assert expected.nnz > 0 and abs(subset_hessian - expected).max() <= 1e-13 * abs(expected).max()


@pytest.mark.parametrize("device", DEVICES)
def test_contact_side_coverage_is_tested_on_the_device(device, monkeypatch):
    """``ContactSides.launch_coverage`` (the GPU's test, read with the gradient's norm): 0 while the subset holds every
    stiff side's neighbours (where ``update`` keeps it), 1 where a stiff point lies on a side with a neighbour outside
    it. With the flag read as 0, ``_contact_subset`` keeps the subset without reading the contact state; a subset of two
    rings holds the one-ring one."""
    solver, ind = _pressed_solver(device=device)
    solver._hessian(ind, 1.0)  # the subset, from the stored contact state
    sides, st = solver._contact_sides, solver._contact_state
    total = solver._q_contact.total_point_count()
    sides.launch_coverage(st.k_normal, st.k_slip, st.k_slip_dir, ind.count, total)
    assert sides.stale.numpy()[0] == 0.0
    mask, points = sides.current.mask.copy(), sides.current.points
    edge = [s for s in np.flatnonzero(mask) if not mask[sides._neighbours[s].indices].all()][0]
    for side, stale in ((np.flatnonzero(~mask)[-1], 1.0), (edge, 1.0), (np.flatnonzero(st.k_normal.numpy())[0] //
                                                                         (points * ind.count), 0.0)):
        k = st.k_normal.numpy().copy()
        k[side * points * ind.count] = 1.0  # a stiff point on that side
        sides.launch_coverage(wp.array(k, dtype=wp.float64, device=device), st.k_slip, st.k_slip_dir, ind.count, total)
        assert sides.stale.numpy()[0] == stale
    monkeypatch.setattr(sides, "update", lambda stiff: pytest.fail("the contact state was read"))
    solver.contact_stale_read(0.0)
    assert solver._contact_subset(ind) is sides.current
    monkeypatch.undo()
    made = []
    for rings in (1, 2):  # each made afresh from the stored contact state
        sides._rings, sides.current, solver._contact_stale = rings, None, None
        made.append(solver._contact_subset(ind).mask)
    assert made[1][made[0]].all() and made[1].sum() > made[0].sum()


def test_contact_sides_are_kept_until_contact_reaches_beyond_them():
    """``ContactSides.update``: the sides with a stiff point and their neighbours; the subset is kept while it holds
    them, grown (their union) when contact spreads, and made from what is needed alone when the union is over twice
    that."""
    solver, _ = _pressed_solver()
    chooser, points = solver._contact_sides, solver._contact_sides.current.points
    sides = chooser.current.mask.size
    stiff = np.zeros((sides, points), dtype=bool)
    stiff[0, 1] = True
    assert chooser.update(stiff.reshape(-1))
    first = chooser.current.mask.copy()
    assert first[0] and 1 < np.count_nonzero(first) < 20  # side 0 and its neighbours
    assert not chooser.update(stiff.reshape(-1))  # the same contact: the subset is kept
    neighbour = np.flatnonzero(first)[-1]
    stiff[neighbour, 0] = True  # contact spreads to a neighbour: its neighbours are added
    assert chooser.update(stiff.reshape(-1)) and np.all(chooser.current.mask[first])
    far = np.flatnonzero(~chooser.current.mask)[-1]
    stiff[:] = False
    stiff[far, 0] = True  # contact elsewhere only: the old subset is dropped (the union would be over twice)
    assert chooser.update(stiff.reshape(-1)) and chooser.current.mask[far] and not chooser.current.mask[0]
    stiff[:] = False
    assert not chooser.update(stiff.reshape(-1))  # nothing touches: nothing to add
