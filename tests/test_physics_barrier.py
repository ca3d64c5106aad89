"""The inversion barrier on det F (elasticity.py): its derivatives, that it is inert above its threshold, and
that it is what lets a press converge where the discrete minimum would otherwise fold elements."""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
import warp as wp
import warp.fem as fem

from transtac_sim.physics import (
    ElasticMaterial,
    QuasiStaticSolver,
    RigidIndenter,
    SolverDidNotConverge,
    SolverSettings,
    elasticity,
)
from transtac_sim.physics.barrier_terms import BarrierHessian
from transtac_sim.physics.box_mesh import box_tet_mesh
from transtac_sim.physics.elasticity import cofactor, cofactor_delta
from transtac_sim.physics.host_factorisation import bsr_to_scipy

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import fem_stability as fs  # noqa: E402

DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() else [])


def _solver(settings: SolverSettings, device: str = "cpu") -> QuasiStaticSolver:
    V, T = box_tet_mesh(np.linspace(0, 2, 3), np.linspace(0, 2, 3), np.linspace(0, 1, 2))
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=2, radius=1.0))
    return QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [sphere], settings, device=device)


def _compressed(solver: QuasiStaticSolver, squeeze: float, seed: int = 0) -> np.ndarray:
    """Dof values of u = (F - I) X with F = diag(1, 1, squeeze), plus a small random field (J varies)."""
    X = solver._space.node_positions().numpy()
    rng = np.random.default_rng(seed)
    return X * np.array([0.0, 0.0, squeeze - 1.0]) + 0.002 * rng.standard_normal(X.shape)


def _far_away(solver):
    P = np.eye(4)
    P[2, 3] = 10.0
    return solver._indenter_struct([P], [P])


@pytest.mark.parametrize("device", DEVICES)
def test_energy_gradient_and_hessian_agree_where_the_barrier_acts(device):
    """Central differences of E along a random direction match g . v, and of g match H v (the exact Hessian),
    at a state whose det F is below the barrier's threshold at some check points (on a GPU the barrier's gradient is
    launched without reading its energy first, assembly.py ``_gradient``)."""
    solver = _solver(SolverSettings(), device)
    ind = _far_away(solver)
    u0 = _compressed(solver, 0.08)
    solver.u.dof_values.assign(wp.array(u0, dtype=wp.vec3d, device=device))
    g = solver._gradient(ind).numpy().copy()  # (on the CPU a view of the kept gradient, which the next call overwrites)
    assert solver._barrier_acts and float(solver._barrier_sum.numpy()[0]) > 0.0  # the barrier acts here
    H = bsr_to_scipy(solver._hessian(ind, geometric=1.0, clamp=False))
    v = np.random.default_rng(1).standard_normal(u0.shape)
    h = 1e-6

    def at(x):
        solver.u.dof_values.assign(wp.array(x, dtype=wp.vec3d, device=device))
        return solver._energy(solver.u, ind), solver._gradient(ind).numpy().copy()

    (e_plus, g_plus), (e_minus, g_minus) = at(u0 + h * v), at(u0 - h * v)
    np.testing.assert_allclose((e_plus - e_minus) / (2 * h), np.sum(g * v), rtol=1e-5)
    np.testing.assert_allclose((g_plus - g_minus).reshape(-1) / (2 * h), H @ v.reshape(-1), rtol=1e-4,
                               atol=1e-5 * np.abs(H @ v.reshape(-1)).max())


@fem.integrand
def _barrier_hessian_form(s: fem.Sample, du: fem.Field, v: fem.Field, F_qp: wp.array(dtype=wp.mat33d),
                          b_qp: wp.array(dtype=wp.vec2d)):
    """The barrier's Hessian integrand (elasticity.py's docstring), for warp.fem's assembly over every tet."""
    F = F_qp[s.qp_index]
    b = b_qp[s.qp_index]
    cof = cofactor(F)
    gdu = fem.grad(du, s)
    gv = fem.grad(v, s)
    return b[1] * wp.ddot(cof, gdu) * wp.ddot(cof, gv) + b[0] * wp.ddot(cofactor_delta(F, gdu), gv)


def _barrier_reference(solver: QuasiStaticSolver):
    """warp.fem's assembly of the barrier's Hessian over every tet, from the check points' F and (s, kappa b'') that
    ``barrier_state_form`` last stored (a scipy matrix)."""
    return bsr_to_scipy(fem.integrate(_barrier_hessian_form, quadrature=solver._q_det,
                                      fields={"du": solver._trial, "v": solver._test},
                                      values={"F_qp": solver._F_det, "b_qp": solver._b_det}, output_dtype=wp.float64))


def _squeezed_along_x(solver: QuasiStaticSolver, noise: float = 0.0, mirrored: bool = False) -> np.ndarray:
    """Dof values squeezing the 2 mm block to det F 0.05 at x = 0 and 0.5 at x = 2 (the barrier acts in some tets, not
    all; ``mirrored``: 0.05 at x = 2 and 0.5 at x = 0), plus ``noise`` mm of a random field."""
    X = solver._space.node_positions().numpy()
    x = 2.0 - X[:, :1] if mirrored else X[:, :1]
    u = X * np.array([0.0, 0.0, 1.0]) * (0.05 + 0.45 * x / 2.0 - 1.0)
    return u + noise * np.random.default_rng(3).standard_normal(X.shape)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", [1, 2])
def test_barrier_hessian_in_its_tets_equals_warp_fems_assembly(device, degree):
    """barrier_terms.py's blocks, added only in the tets where the barrier acts, equal warp.fem's assembly of the
    integrand over every tet: exact, clamped and Gauss-Newton, at a state squeezed to det F 0.05 at one end of the
    block and 0.5 at the other (the barrier acts in some tets, not all)."""
    solver = _solver(SolverSettings(degree=degree), device)
    solver.u.dof_values.assign(wp.array(_squeezed_along_x(solver, 0.002), dtype=wp.vec3d, device=device))
    total = wp.sparse.bsr_copy(solver._deviatoric().H)
    barrier = BarrierHessian.make(solver._barrier_check_points(), total, solver.device)
    values = {"F_qp": solver._F_det, "b_qp": solver._b_det}
    for geometric, clamp in ((1.0, elasticity.EXACT), (1.0, elasticity.CLAMPED), (0.0, elasticity.CLAMPED)):
        solver._barrier_tets.zero_()
        fem.interpolate(elasticity.barrier_state_form, at=solver._q_det, fields={"u": solver.u},
                        values=solver._barrier_values() | values | {"geometric": geometric, "clamp": clamp,
                                                                    "barrier_tets": solver._barrier_tets})
        acting = int(solver._barrier_tets.numpy().sum())
        assert 0 < acting < len(solver.tets)
        expected = _barrier_reference(solver)
        total.values.zero_()
        barrier.add_to(total, solver._F_det, solver._b_det, solver._barrier_tets)
        assert expected.nnz > 0 and abs(bsr_to_scipy(total) - expected).max() <= 1e-12 * abs(expected).max()


def test_summed_hessian_adds_the_barrier_where_it_acts():
    """The Newton matrix (hessian_assembly.py ``_hessian``) where the barrier acts in some tets equals the one without
    the barrier plus warp.fem's assembly of the barrier's integrand over every tet (the exact Hessian, whose volumetric
    part does not depend on where the barrier acts)."""
    with_barrier, without = _solver(SolverSettings()), _solver(SolverSettings(barrier_det_f=0.0))
    u = _squeezed_along_x(with_barrier)
    summed = []
    for solver in (with_barrier, without):
        ind = _far_away(solver)
        solver.u.dof_values.assign(wp.array(u, dtype=wp.vec3d))
        solver._gradient(ind)
        summed.append(bsr_to_scipy(solver._hessian(ind, geometric=1.0, clamp=elasticity.EXACT)))
    acting = int(with_barrier._barrier_tets.numpy().sum())
    assert with_barrier._barrier_acts and 0 < acting < len(with_barrier.tets)
    barrier = _barrier_reference(with_barrier)
    assert barrier.nnz > 0 and abs(summed[0] - summed[1] - barrier).max() <= 1e-11 * abs(barrier).max()


@fem.integrand
def _barrier_gradient_form(s: fem.Sample, u: fem.Field, v: fem.Field, params: wp.array(dtype=wp.vec2d),
                           stiffness: wp.float64, j_hat: wp.float64):
    """The barrier's gradient integrand (barrier_terms.py's docstring), for warp.fem's integration over every tet."""
    F = elasticity.deformation_gradient(fem.grad(u, s))
    db = elasticity.det_barrier(wp.determinant(F), j_hat)[1]
    return stiffness * params[s.element_index][0] * db * wp.ddot(cofactor(F), fem.grad(v, s))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("degree", [1, 2])
def test_barrier_gradient_in_its_tets_equals_warp_fems_integration(device, degree):
    """barrier_terms.py's gradient, added only in the tets where some det F is below j_hat, equals warp.fem's
    integration of the integrand over every tet's check points, at a state squeezed to det F 0.05 at one end of the
    block and 0.5 at the other, and at its mirror image (the barrier acts in some tets, not all, and in some only at
    some of their check points, on either side); above the threshold everywhere it adds nothing."""
    solver = _solver(SolverSettings(degree=degree), device)
    check = solver._barrier_check_points()
    s = solver.settings
    for u, acts in ((_squeezed_along_x(solver, 0.002), True), (_squeezed_along_x(solver, 0.002, mirrored=True), True),
                    (0.1 * _squeezed_along_x(solver), False)):
        solver.u.dof_values.assign(wp.array(u, dtype=wp.vec3d, device=device))
        expected = fem.integrate(_barrier_gradient_form, quadrature=solver._q_det,
                                 fields={"u": solver.u, "v": solver._test},
                                 values=solver._barrier_values(), output_dtype=wp.vec3d).numpy()
        g = wp.zeros(len(u), dtype=wp.vec3d, device=device)
        check.add_gradient_to(g, solver.u.dof_values, solver._params, s.barrier_stiffness, s.barrier_det_f)
        if acts:
            assert np.abs(expected).max() > 0.0
            np.testing.assert_allclose(g.numpy(), expected, rtol=0, atol=1e-12 * np.abs(expected).max())
        else:
            assert not expected.any() and not g.numpy().any()


@pytest.mark.parametrize("device", DEVICES)
def test_barrier_is_inert_above_its_threshold(device):
    """Above the threshold the barrier adds nothing: E and g as without it (on a GPU its gradient's kernel is launched
    anyway and returns at once in every tet)."""
    on, off = _solver(SolverSettings(), device), _solver(SolverSettings(barrier_det_f=0.0), device)
    for s in (on, off):
        s.u.dof_values.assign(wp.array(_compressed(s, 0.8), dtype=wp.vec3d, device=device))
    ind_on, ind_off = _far_away(on), _far_away(off)
    on._gradient(ind_on)
    assert not on._barrier_acts and float(on._barrier_sum.numpy()[0]) == 0.0
    assert on._energy(on.u, ind_on) == off._energy(off.u, ind_off)
    np.testing.assert_array_equal(on._gradient(ind_on).numpy(), off._gradient(ind_off).numpy())  # two solvers' own


BLOCK = fs.Block(width=6.0, thickness=3.0, h_fine=1.0, fine_half_width=2.0)


@pytest.mark.parametrize("barrier", [False, True])
def test_half_thickness_press_needs_the_barrier(barrier, monkeypatch):
    """The sphere pressed to 50 % of the coarse block: without the barrier an element under its rim inverts at
    the discrete minimum (a clear SolverDidNotConverge at frame 3, sub-steps down to 1/32 of its motion tried);
    with it every frame converges with det F > 0 and the force keeps rising."""
    case = next(c for c in fs.cases() if c.name == "depth 50 % of thickness")
    if not barrier:
        monkeypatch.setattr(fs, "SolverSettings", lambda **kw: replace(SolverSettings(**kw), barrier_det_f=0.0))
    r = fs.run_case(case, BLOCK)
    if not barrier:
        assert isinstance(r.error, SolverDidNotConverge) and "frame 3 " in str(r.error)
        assert "sub-steps down to 1/32 of its motion" in str(r.error) and "inverted element" in str(r.error)
        return
    assert r.error is None and len(r.frames) == 5
    assert all(f["min_det_f"] > 0.0 and f["max_penetration_mm"] <= 0.02 + 1e-9 for f in r.frames)
    fz = np.array([f["fz"] for f in r.frames])
    assert np.all(np.diff(-fz) > 0.0), fz


@pytest.mark.parametrize("squeeze", [0.2, 0.08, 0.03])
def test_clamped_hessian_is_positive_definite_where_the_barrier_acts(squeeze):
    """Newton's second Hessian (the clamped one, newton.py ``_hessian_ladder``) on the free dofs is positive definite
    in compression, also where det F is below the barrier's threshold (squeeze 0.08, 0.03) and its clamped term adds
    to the volumetric pressure's; the exact Hessian there is not (what makes Newton fall back to the clamped one)."""
    solver = _solver(SolverSettings())
    ind = _far_away(solver)
    solver.u.dof_values.assign(wp.array(_compressed(solver, squeeze), dtype=wp.vec3d))
    solver._gradient(ind)
    assert solver._barrier_acts == (squeeze < 0.1)
    free = ~solver._fixed_nodes.reshape(-1)

    def extreme_eigenvalues(clamp: bool):
        H = bsr_to_scipy(solver._hessian(ind, geometric=1.0, clamp=clamp)).toarray()[free][:, free]
        ev = np.linalg.eigvalsh(0.5 * (H + H.T))
        return ev[0], ev[-1]

    lowest, highest = extreme_eigenvalues(clamp=True)
    assert lowest > 1e-4 * highest  # measured: 1.9e-4 (0.03) to 4.2e-3 (0.2)
    assert extreme_eigenvalues(clamp=False)[0] < 0.0


def test_clamped_hessian_is_positive_semidefinite_in_every_state_tried():
    """The clamped Hessian, before any fixed dof is projected out, is positive semi-definite by construction
    (elasticity.py: the deviatoric term covers the clamped volumetric and barrier terms, each clamped to half where
    both act). Random compressed states of a 6-tet cube at nu = 0.49, det F down to 0.03: its lowest eigenvalue is
    round-off. With both terms clamped to the whole bound the same states gave eigenvalues down to -4e-4 x the largest
    where the barrier acts."""
    V, T = box_tet_mesh(np.linspace(0, 1, 2), np.linspace(0, 1, 2), np.linspace(0, 1, 2))
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=2, radius=1.0))
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.49), [sphere], SolverSettings())
    ind = _far_away(solver)
    X = solver._space.node_positions().numpy()
    lowest, barrier_states = [], 0
    for seed in range(60):
        rng = np.random.default_rng(seed)
        F = np.diag([rng.uniform(0.9, 1.6), rng.uniform(0.9, 1.6), rng.uniform(0.03, 0.3)])
        u = X @ (F - np.eye(3)).T + rng.uniform(0.005, 0.05) * rng.standard_normal(X.shape)
        solver.u.dof_values.assign(wp.array(u, dtype=wp.vec3d))
        if solver._min_det(solver.u) <= 0.0:
            continue
        solver._gradient(ind)
        barrier_states += solver._barrier_acts
        H = bsr_to_scipy(solver._hessian(ind, geometric=1.0, clamp=True)).toarray()
        ev = np.linalg.eigvalsh(0.5 * (H + H.T))
        lowest.append(ev[0] / ev[-1])
    assert len(lowest) >= 30 and barrier_states >= 10
    assert min(lowest) > -1e-12, min(lowest)
