"""The device CG that stops at non-positive curvature (physics/definite_cg.py), against scipy and a numpy PCG; on the CPU,
and on a GPU where there is one (the device tool, not CI)."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp
from pcg_reference import diagonal_block_inverses, pcg_iterate

from transtac_sim.physics.cg_kernels import CgWorkspace
from transtac_sim.physics.definite_cg import CHECK_EVERY, UNROLL, definite_cg
from transtac_sim.physics.sparse_product import (
    BlockJacobi,
    block_row_operator,
    invert_diagonal,
    round_to_float32,
)

N = 200  # 3-vectors
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() else [])


def _laplacian_3d(shift: float) -> sp.csr_matrix:
    """A 1D chain Laplacian of N nodes with 3 coupled components per node (symmetric), minus ``shift`` I: its
    eigenvalues lie within [0.47, 5.6] - shift (the chain's in [0, 4], the coupling's in [0.47, 1.6]), so shift = 0
    is positive definite and shift = 1 is not (checked)."""
    lap = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(N, N))
    coupling = np.array([[1.5, 0.2, 0.0], [0.2, 1.0, 0.1], [0.0, 0.1, 0.5]])
    return (sp.kron(lap, np.eye(3)) + sp.kron(sp.eye(N), coupling) - shift * sp.eye(3 * N)).tocsr()


def _warp_bsr(A: sp.csr_matrix, device=None):
    B = A.tobsr(blocksize=(3, 3))
    B.sort_indices()
    rows = np.repeat(np.arange(N), np.diff(B.indptr))
    return wp.sparse.bsr_from_triplets(N, N, wp.array(rows, dtype=int, device=device),
                                       wp.array(B.indices, dtype=int, device=device),
                                       wp.array(B.data, dtype=wp.mat33d, device=device))


@pytest.mark.parametrize("jacobi", [False, True])
def test_definite_cg_solves_a_positive_definite_system_to_its_tolerance(jacobi: bool):
    A = _laplacian_3d(0.0)
    H = _warp_bsr(A)
    b = np.random.default_rng(0).standard_normal((N, 3))
    x = wp.zeros(N, dtype=wp.vec3d)
    M = BlockJacobi(H) if jacobi else None
    result = definite_cg(block_row_operator(H), wp.array(b, dtype=wp.vec3d), x, 1e-10, 3 * N, M)
    assert result.converged and not result.not_definite and 0 < result.iterations <= 3 * N
    assert result.x_max == np.abs(x.numpy()).max()
    assert result.x_dot_b == pytest.approx(float(np.sum(x.numpy() * b)), rel=1e-12)
    residual = np.linalg.norm(A @ x.numpy().reshape(-1) - b.reshape(-1))
    assert residual <= 1e-10 * np.linalg.norm(b)
    np.testing.assert_allclose(x.numpy().reshape(-1), spla.spsolve(A.tocsc(), b.reshape(-1)), rtol=1e-7, atol=1e-9)
    # started at the solution it does nothing; a loose tolerance stops it early
    again = definite_cg(block_row_operator(H), wp.array(b, dtype=wp.vec3d), x, 1e-8, 3 * N, M)
    assert again.converged and again.iterations == 0
    loose = definite_cg(block_row_operator(H), wp.array(b, dtype=wp.vec3d), wp.zeros(N, dtype=wp.vec3d), 1e-2,
                        3 * N, M)
    assert loose.converged and loose.iterations < result.iterations


def test_definite_cg_stops_where_the_matrix_is_not_positive_definite():
    A = _laplacian_3d(1.0)
    assert spla.eigsh(A, k=1, which="SA")[0][0] < 0.0
    H = _warp_bsr(A)
    b = np.random.default_rng(1).standard_normal((N, 3))
    result = definite_cg(block_row_operator(H), wp.array(b, dtype=wp.vec3d), wp.zeros(N, dtype=wp.vec3d), 1e-10,
                         10 * N)
    assert result.not_definite and not result.converged and result.iterations < 3 * N
    start = np.ones((N, 3))
    start[7, 1] = np.nan  # a broken start: stopped before any iteration, and its x_max is NaN (never a short step)
    broken = definite_cg(block_row_operator(_warp_bsr(_laplacian_3d(0.0))), wp.array(b, dtype=wp.vec3d),
                         wp.array(start, dtype=wp.vec3d), 1e-10, 3 * N)
    assert not broken.converged and broken.iterations == 0 and np.isnan(broken.x_max)


def test_definite_cg_reports_its_iteration_cap():
    H = _warp_bsr(_laplacian_3d(0.0))
    b = wp.array(np.random.default_rng(2).standard_normal((N, 3)), dtype=wp.vec3d)
    result = definite_cg(block_row_operator(H), b, wp.zeros(N, dtype=wp.vec3d), 1e-12, 5)
    assert not result.converged and not result.not_definite and result.iterations == 5


def _numpy_pcg(A: sp.csr_matrix, b: np.ndarray, iterations: int) -> np.ndarray:
    """x after ``iterations`` steps of block-Jacobi PCG from 0."""
    blocks = diagonal_block_inverses(A)
    return pcg_iterate(A, b, lambda v: (blocks @ v.reshape(-1, 3, 1)).reshape(-1), iterations)


@pytest.mark.parametrize("device", DEVICES)
def test_iterations_after_the_cap_change_nothing(device: str):
    """Stopped by its cap at every count up to two of the CUDA loop's passes (``UNROLL`` iterations each, the ones
    after the stop within a pass run as no-ops), x is the k-th PCG iterate: none of those no-op iterations moves it."""
    A = _laplacian_3d(0.0)
    H = _warp_bsr(A, device)
    b = np.random.default_rng(5).standard_normal(3 * N)
    M = BlockJacobi(H)
    for cap in range(1, 2 * UNROLL + 2):
        x = wp.zeros(N, dtype=wp.vec3d, device=device)
        result = definite_cg(block_row_operator(H), wp.array(b.reshape(N, 3), dtype=wp.vec3d, device=device), x,
                             1e-14, cap, M)
        assert result.iterations == cap and not result.converged, (cap, result)
        expected = _numpy_pcg(A, b, cap)
        np.testing.assert_allclose(x.numpy().reshape(-1), expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


@pytest.mark.skipif(not wp.get_cuda_device_count(), reason="needs a GPU (the device tool, not CI)")
def test_cuda_without_conditional_graphs_gives_the_same_iterates(monkeypatch):
    """Where the driver has no conditional graphs, the first pass of the loop runs as it loads the kernels, and one
    captured pass (its sets 0, 1, 2) is launched ``CHECK_EVERY`` times between reads of the state: x at each cap
    within and beyond those launches is still the k-th PCG iterate, from a fresh workspace and from a kept one."""
    monkeypatch.setattr(wp, "is_conditional_graph_supported", lambda: False)
    A = _laplacian_3d(0.0)
    H = _warp_bsr(A, "cuda:0")
    b = np.random.default_rng(6).standard_normal(3 * N)
    M, workspace, kept_x = BlockJacobi(H), CgWorkspace(N, "cuda:0"), wp.zeros(N, dtype=wp.vec3d, device="cuda:0")
    for cap in (1, 2, 3, 4, UNROLL * (CHECK_EVERY + 1) + 1):
        for kept in (None, workspace):
            x = wp.zeros(N, dtype=wp.vec3d, device="cuda:0") if kept is None else kept_x
            x.zero_()
            result = definite_cg(block_row_operator(H), wp.array(b.reshape(N, 3), dtype=wp.vec3d, device="cuda:0"), x,
                                 1e-14, cap, M, workspace=kept)
            assert result.iterations == cap and not result.converged, (cap, result)
            expected = _numpy_pcg(A, b, cap)
            np.testing.assert_allclose(x.numpy().reshape(-1), expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
    assert workspace.captures == 1  # the kept workspace's later solves launched its graph without a first pass


def test_block_jacobi_applies_the_inverse_diagonal_blocks():
    A = _laplacian_3d(0.0)
    M = BlockJacobi(_warp_bsr(A))
    x, y = np.random.default_rng(3).standard_normal((2, N, 3))
    z = wp.zeros(N, dtype=wp.vec3d)
    M.matvec(wp.array(x, dtype=wp.vec3d), wp.array(y, dtype=wp.vec3d), z, 0.5, 2.0)
    diagonal = np.stack([A[3 * i:3 * i + 3, 3 * i:3 * i + 3].toarray() for i in range(N)])
    expected = 0.5 * np.linalg.solve(diagonal, x[:, :, None])[:, :, 0] + 2.0 * y
    np.testing.assert_allclose(z.numpy(), expected, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("device", DEVICES)
def test_kept_workspace_solves_as_a_fresh_one(device: str):
    """Solves that share a workspace (its vectors, state and, on CUDA, the graph captured by the first: linear.py's
    Newton systems) give what a fresh solve gives, with another right-hand side, tolerance and iteration cap, and after
    the matrix's values change in the same arrays; on CUDA only the first solve captures a graph. Run on the CPU, and
    on a GPU where there is one (the device tool, not CI)."""
    A = _laplacian_3d(0.0)
    H = _warp_bsr(A, device)
    rounded = wp.empty(len(H.values), dtype=wp.mat33f, device=device)
    inverse = wp.empty(N, dtype=wp.mat33d, device=device)
    workspace, x = CgWorkspace(N, device), wp.zeros(N, dtype=wp.vec3d, device=device)
    rng = np.random.default_rng(4)

    def solve(b, rtol, maxiter, kept: bool, start=None):
        op = block_row_operator(H, single_precision=True, rounded=rounded)
        M = BlockJacobi(H, inverse=inverse)
        out = x if kept else wp.zeros(N, dtype=wp.vec3d, device=device)
        out.assign(np.zeros((N, 3)) if start is None else start)
        result = definite_cg(op, wp.array(b, dtype=wp.vec3d, device=device), out, rtol, maxiter, M,
                             workspace=workspace if kept else None)
        return result, out.numpy()

    exact = spla.spsolve(A.tocsc(), np.ones(3 * N)).reshape(N, 3)
    cases = [  # b, rtol, maxiter, start
        (rng.standard_normal((N, 3)), 1e-10, 3 * N, None),
        (rng.standard_normal((N, 3)), 1e-6, 7, None),  # stopped by its cap
        (1e3 * rng.standard_normal((N, 3)), 1e-2, 3 * N, None),  # a loose solve of a large b ...
        (1e-3 * rng.standard_normal((N, 3)), 1e-8, 3 * N, None),  # ... then a small b: no tolerance carried over
        (np.ones((N, 3)), 1e-6, 3 * N, exact),  # converged at its start: returns before any iteration ...
        (1e-4 * rng.standard_normal((N, 3)), 1e-6, 3 * N, None),  # ... and leaves nothing in the state
    ]
    tol = 1e-12 if device == "cpu" else 1e-9  # on CUDA the dot products' atomics change the last bits
    for b, rtol, maxiter, start in cases:
        kept, x_kept = solve(b, rtol, maxiter, kept=True, start=start)
        fresh, x_fresh = solve(b, rtol, maxiter, kept=False, start=start)
        assert kept.converged == fresh.converged and abs(kept.iterations - fresh.iterations) <= (device != "cpu"), \
            (kept, fresh)
        assert kept.iterations > 0 or start is not None, kept
        assert (maxiter > 7 or kept.iterations == 7) and (start is None or kept.iterations == 0), kept
        np.testing.assert_allclose(x_kept, x_fresh, rtol=tol, atol=tol * np.abs(x_fresh).max())
        assert kept.x_max == np.abs(x_kept).max() and fresh.x_max == np.abs(x_fresh).max()  # read with the state
    H.values.assign(2.0 * H.values.numpy())  # the same arrays, another matrix: the solution halves
    b = rng.standard_normal((N, 3))
    before = spla.spsolve(A.tocsc(), b.reshape(-1))
    kept, x_kept = solve(b, 1e-10, 3 * N, kept=True)
    assert kept.converged and kept.x_max == np.abs(x_kept).max()
    np.testing.assert_allclose(x_kept.reshape(-1), 0.5 * before, rtol=1e-5, atol=1e-7 * np.abs(before).max())
    assert workspace.captures == (1 if device != "cpu" else 0)


@pytest.mark.parametrize("device", DEVICES)
def test_a_set_up_made_by_the_caller_solves_as_the_operators_own(device):
    """device_linear.py's set-up: the float32 blocks and the diagonal inverses written by the caller
    (``round_to_float32``, ``invert_diagonal``: replayed as one graph there) and b written into the workspace's own
    ``b`` (nothing copied) give the iterates of the operators that make their own; the operators refuse to be made
    without the arrays they would read."""
    A = _laplacian_3d(0.0)
    H = _warp_bsr(A, device)
    b = wp.array(np.random.default_rng(5).standard_normal((N, 3)), dtype=wp.vec3d, device=device)
    own_x = wp.zeros(N, dtype=wp.vec3d, device=device)
    own = definite_cg(block_row_operator(H, single_precision=True), b, own_x, 1e-8, 3 * N, BlockJacobi(H))
    rounded = wp.empty(len(H.values), dtype=wp.mat33f, device=device)
    inverse = wp.empty(N, dtype=wp.mat33d, device=device)
    round_to_float32(H, rounded)
    invert_diagonal(H, inverse)
    workspace, x = CgWorkspace(N, device), wp.zeros(N, dtype=wp.vec3d, device=device)
    wp.copy(workspace.b, b)
    caller = definite_cg(block_row_operator(H, single_precision=True, rounded=rounded, round_now=False),
                         workspace.b, x, 1e-8, 3 * N, BlockJacobi(H, inverse=inverse, invert_now=False),
                         workspace=workspace)
    assert caller.converged and caller.iterations == own.iterations
    tol = 0.0 if device == "cpu" else 1e-9  # on CUDA the dot products' atomics change the last bits
    np.testing.assert_allclose(x.numpy(), own_x.numpy(), rtol=0.0, atol=tol * np.abs(own_x.numpy()).max())
    with pytest.raises(ValueError, match="round_now"):
        block_row_operator(H, single_precision=True, round_now=False)
    with pytest.raises(ValueError, match="float32 buffer"):  # a buffer the caller filled must hold every block too
        block_row_operator(H, single_precision=True, rounded=rounded[:-1], round_now=False)
    with pytest.raises(ValueError, match="invert_now"):
        BlockJacobi(H, invert_now=False)
    with pytest.raises(ValueError, match="float32 buffer"):
        round_to_float32(H, wp.empty(len(H.values) - 1, dtype=wp.mat33f, device=device))


@pytest.mark.parametrize("device", DEVICES)
def test_a_solve_that_takes_b_and_starts_from_zero_solves_the_projected_system(device):
    """``fixed`` and ``from_zero`` (device_linear.py's solves): the solve's first launch takes (I - P) b from the
    caller's kept b and sets x = 0, inside its graph on CUDA; whatever x held, it gives the iterates of a solve of the
    projected b from 0, sees b's new values on each replay, and refines from where it stopped without ``from_zero``; on
    CUDA one graph serves both starts (whether x = 0 first is copied in with the limits)."""
    A = _laplacian_3d(0.0)
    H = _warp_bsr(A, device)
    rng = np.random.default_rng(7)
    mask = np.zeros((N, 3))
    mask[0] = 1.0
    mask[5, 2] = 1.0
    fixed = wp.array(mask, dtype=wp.vec3d, device=device)
    workspace, b, x = CgWorkspace(N, device), wp.empty(N, dtype=wp.vec3d, device=device), wp.empty(N, dtype=wp.vec3d,
                                                                                                     device=device)
    tol = 0.0 if device == "cpu" else 1e-9  # on CUDA the dot products' atomics change the last bits
    A_op, M = block_row_operator(H), BlockJacobi(H)  # the same arrays in each solve: its graphs are kept
    for _ in range(3):  # launched, captured, replayed
        values = rng.standard_normal((N, 3))
        b.assign(values)
        x.fill_(1.0e3)  # not where the solve starts
        taken = definite_cg(A_op, b, x, 1e-2, 3 * N, M, workspace=workspace, fixed=fixed, from_zero=True)
        reference_x = wp.zeros(N, dtype=wp.vec3d, device=device)
        reference = definite_cg(block_row_operator(H), wp.array(values * (1.0 - mask), dtype=wp.vec3d, device=device),
                                reference_x, 1e-2, 3 * N, BlockJacobi(H))
        assert taken.converged and abs(taken.iterations - reference.iterations) <= (device != "cpu"), (taken, reference)
        np.testing.assert_allclose(x.numpy(), reference_x.numpy(), rtol=0.0,
                                   atol=tol * np.abs(reference_x.numpy()).max())
        refined = definite_cg(A_op, b, x, 1e-10, 3 * N, M, workspace=workspace, fixed=fixed)
        assert refined.converged and refined.iterations > 0
        exact = spla.spsolve(A.tocsc(), (values * (1.0 - mask)).reshape(-1))
        np.testing.assert_allclose(x.numpy().reshape(-1), exact, rtol=1e-7, atol=1e-9 * np.abs(exact).max())
    assert workspace.captures == (1 if device != "cpu" else 0)
    with pytest.raises(ValueError, match="a fixed mask of 3 nodes"):
        definite_cg(A_op, b, x, 1e-2, 3 * N, M, workspace=workspace, fixed=fixed[:3])
