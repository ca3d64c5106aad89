"""The device CG's matrix-vector product (physics/sparse_product.py) against scipy, its projection of the fixed
degrees of freedom (physics/linear.py) against warp.fem's, and its last resort (a shifted system) against scipy's
solve, on a real Newton Hessian."""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import trimesh
import warp as wp
import warp.fem as fem

from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter
from transtac_sim.physics.box_mesh import gel_block
from transtac_sim.physics.linear import SHIFTS, LinearSolver, _project_fixed_blocks, bsr_to_scipy
from transtac_sim.physics.sparse_product import block_row_operator


def _pressed_solver():
    """A sphere pressed 0.3 mm into a small P2 block (friction 0.5), and its indenter struct, with the contact state
    of the solution stored."""
    V, T = gel_block(6.0, 6.0, 2.0, h_fine=0.6, fine_half_width=1.2, growth=2.0)
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=3, radius=2.0), 0.5)
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [sphere])
    P = np.eye(4)
    P[2, 3] = 4.0 + 1e-3
    solver.start([P])
    Q = P.copy()
    Q[2, 3] = 4.0 - 0.3
    solver.solve_frame([Q])
    ind = solver._indenter_struct([Q], [Q])
    solver._gradient(ind)  # stores the contact state the Hessian uses
    return solver, ind


def _pressed_hessian():
    """The summed Newton Hessian (elastic, barrier where it acts, contact with friction) of ``_pressed_solver``, as
    the device CG receives it."""
    solver, ind = _pressed_solver()
    return wp.sparse.bsr_copy(solver._hessian(ind, 1.0, True))


def test_block_row_product_matches_scipy():
    H = _pressed_hessian()
    A = bsr_to_scipy(H)
    assert A.nnz > 0 and abs(A - A.T).max() < 1e-9 * abs(A).max()  # a symmetric Newton matrix with contact terms
    rng = np.random.default_rng(1)
    x, y = rng.standard_normal((2, H.nrow, 3))
    z = wp.zeros(H.nrow, dtype=wp.vec3d)
    block_row_operator(H).matvec(wp.array(x, dtype=wp.vec3d), wp.array(y, dtype=wp.vec3d), z, 0.7, -1.3)
    expected = 0.7 * (A @ x.reshape(-1)) - 1.3 * y.reshape(-1)
    np.testing.assert_allclose(z.numpy().reshape(-1), expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    z2 = wp.array(y, dtype=wp.vec3d)  # beta = 0 ignores y, and z may be y
    block_row_operator(H).matvec(wp.array(x, dtype=wp.vec3d), z2, z2, 1.0, 0.0)
    np.testing.assert_allclose(z2.numpy().reshape(-1), A @ x.reshape(-1), rtol=1e-12,
                               atol=1e-12 * np.abs(A @ x.reshape(-1)).max())


def test_fixed_projection_matches_warp_fem():
    """(I - P) H (I - P) + P in place, block by block, equals warp.fem.project_linear_system's sparse products."""
    H = _pressed_hessian()
    fixed = np.random.default_rng(0).random((H.nrow, 3)) < 0.2  # components fixed at random, some nodes partly
    blocks = np.zeros((H.nrow, 3, 3))
    blocks[:, [0, 1, 2], [0, 1, 2]] = fixed
    by_fem = wp.sparse.bsr_copy(H)
    fem.project_linear_system(by_fem, wp.zeros(H.nrow, dtype=wp.vec3d), wp.sparse.bsr_diag(wp.array(blocks, dtype=wp.mat33d)),
                              normalize_projector=False)
    wp.launch(_project_fixed_blocks, dim=H.nrow, inputs=[H.offsets, H.row_counts, H.columns, H.values,
                                                         wp.array(fixed.astype(np.float64), dtype=wp.vec3d)])
    A, B = bsr_to_scipy(by_fem), bsr_to_scipy(H)
    assert abs(A - B).max() <= 1e-14 * abs(A).max() and abs(A - bsr_to_scipy(_pressed_hessian())).max() > 0.0


def test_summed_hessian_equals_the_sum_of_its_parts():
    """assembly.py adds each Hessian part into one kept matrix through precomputed block places: the result equals
    scipy's sum of the parts (deviatoric, volumetric, contact with friction), and a second assembly overwrites the
    first instead of adding to it."""
    solver, ind = _pressed_solver()
    first = bsr_to_scipy(solver._hessian(ind, 1.0, False))
    H = bsr_to_scipy(solver._hessian(ind, 1.0, False))
    parts = [bsr_to_scipy(solver._H_dev)] + [bsr_to_scipy(M) for M in solver._H_parts.values()]
    assert set(solver._H_parts) >= {"volumetric", "contact"} and bsr_to_scipy(solver._H_parts["contact"]).nnz > 0
    expected = sum(parts[1:], parts[0])
    assert abs(H - expected).max() <= 1e-13 * abs(expected).max()
    assert abs(first - H).max() <= 1e-13 * abs(expected).max()  # not accumulated over the two calls


def test_device_last_resort_solves_the_shifted_system():
    """Newton's last Hessian (Gauss-Newton, ``definite=False``) that the device CG does not solve (here: 8 iterations
    allowed, to a relative residual of 1e-10) is solved with a Levenberg-Marquardt shift, H + lambda |diag H|
    (linear.py ``SHIFTS``): the step equals scipy's solution of that shifted system on the free dofs and is a descent
    direction. A Hessian that must be positive definite returns None instead, and so does the last one where no
    shift converges (1 iteration allowed); nothing is handed to the host."""
    solver, ind = _pressed_solver()
    linear = LinearSolver("cg", solver._fixed_nodes, solver.device)
    linear.cg_maxiter = 8
    g = solver._gradient(ind).numpy()
    g[solver._fixed_nodes] = 0.0
    rhs = wp.array(-g, dtype=wp.vec3d)
    H = solver._hessian(ind, 0.0, True)
    projected = wp.sparse.bsr_copy(H)
    wp.launch(_project_fixed_blocks, dim=H.nrow, inputs=[projected.offsets, projected.row_counts, projected.columns,
                                                         projected.values, linear._fixed])
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
