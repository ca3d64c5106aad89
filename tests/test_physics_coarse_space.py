"""The device CG's coarse level (physics/coarse_space.py): its Galerkin operator against numpy, its inverse, and the
two-level CG against scipy's solution and block-Jacobi's iteration count. On the CPU, and on a GPU where there is one
(the device tool, not CI)."""

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import warp as wp
from pcg_reference import diagonal_block_inverses, pcg_iterate

from transtac_sim.physics.coarse_space import CoarseSpace, _aggregates, basis_matrices, coarse_inverse
from transtac_sim.physics.definite_cg import definite_cg
from transtac_sim.physics.sparse_product import BlockJacobi, block_row_operator

SHAPE = (24, 20, 4)  # grid nodes along x, y, z (1 mm apart); the z = 0 layer is fixed
DEVICES = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() else [])


def _grid_system(shape: tuple[int, int, int] = SHAPE):
    """A vector Laplacian on a 3D grid of nodes (each node coupled to its 6 neighbours through a symmetric positive
    definite 3x3 block) with the bottom layer fixed as the solver projects it (identity rows and columns): node
    positions (mm), fixed mask, the 3x3-block matrix (scipy CSR, symmetric positive definite)."""
    idx = np.arange(np.prod(shape)).reshape(shape)
    positions = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    pairs = np.concatenate([np.stack([np.take(idx, range(0, shape[a] - 1), axis=a).ravel(),
                                      np.take(idx, range(1, shape[a]), axis=a).ravel()], 1) for a in range(3)])
    n = len(positions)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    graph = graph + graph.T
    laplacian = sp.diags(np.asarray(graph.sum(axis=1)).ravel()) - graph
    coupling = np.array([[1.5, 0.2, 0.0], [0.2, 1.0, 0.1], [0.0, 0.1, 0.5]])
    A = sp.kron(laplacian, coupling).tolil()
    fixed = np.repeat((positions[:, 2] == 0.0)[:, None], 3, axis=1)
    for k in np.flatnonzero(fixed.reshape(-1)):
        A[k, :] = 0.0
        A[:, k] = 0.0
        A[k, k] = 1.0
    return positions, fixed, A.tocsr()


def _warp_bsr(A: sp.csr_matrix, device: str):
    B = A.tobsr(blocksize=(3, 3))
    B.sort_indices()
    rows = np.repeat(np.arange(B.shape[0] // 3), np.diff(B.indptr))
    return wp.sparse.bsr_from_triplets(B.shape[0] // 3, B.shape[0] // 3, wp.array(rows, dtype=int, device=device),
                                       wp.array(B.indices, dtype=int, device=device),
                                       wp.array(B.data, dtype=wp.mat33d, device=device))


def _prolongation(coarse: CoarseSpace) -> sp.csr_matrix:
    """P (3 nodes x 6 aggregates) from the coarse space's per-node blocks B_i (its arms and free masks)."""
    basis, aggregate = basis_matrices(coarse.arm.numpy(), coarse.free.numpy() == 0.0), coarse.aggregate.numpy()
    n = len(aggregate)
    rows = np.repeat(np.arange(3 * n), 6)
    cols = (6 * aggregate[:, None, None] + np.arange(6)[None, None, :]).repeat(3, axis=1).reshape(-1)
    return sp.csr_matrix((basis.reshape(-1), (rows, cols)), shape=(3 * n, coarse.size))


@pytest.mark.parametrize("device", DEVICES)
def test_galerkin_operator_is_p_transpose_h_p_with_rigid_modes_and_free_masks(device: str):
    positions, fixed, A = _grid_system()
    coarse = CoarseSpace(positions, fixed, 3.0, device)
    P = _prolongation(coarse)
    np.testing.assert_allclose(coarse.galerkin(_warp_bsr(A, device)), (P.T @ A @ P).toarray(), rtol=1e-12, atol=1e-10)
    # P's columns are the aggregates' translations and rotations w x c on the free components, 0 on the fixed ones
    assert np.all(P.toarray()[fixed.reshape(-1)] == 0.0)
    node = int(np.flatnonzero(~fixed[:, 0])[7])
    a = int(coarse.aggregate.numpy()[node])
    y = np.zeros(coarse.size)
    y[6 * a:6 * a + 6] = [0.1, -0.2, 0.3, 0.01, 0.02, -0.03]
    members = coarse.aggregate.numpy() == a
    centroid = positions[members & ~fixed[:, 0]].mean(axis=0)
    expected = y[6 * a:6 * a + 3] + np.cross(y[6 * a + 3:6 * a + 6], positions[node] - centroid)
    np.testing.assert_allclose((P @ y).reshape(-1, 3)[node], expected, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cell_mm", [3.0, 12.0])
def test_restriction_and_coarse_product_are_p_transpose_and_the_inverse(device: str, cell_mm: float):
    """``solve``: P^T r summed per aggregate (one thread group each, no atomics; with 12 mm cells, aggregates of about
    360 nodes, more than a group's 128 threads), written over what was there, then the float32 inverse's product and
    (P^T r) . A_c^-1 P^T r added to the given slot."""
    positions, fixed, A = _grid_system()
    coarse = CoarseSpace(positions, fixed, cell_mm, device)
    assert coarse.update(_warp_bsr(A, device))
    assert (cell_mm < 10.0) or np.bincount(coarse.aggregate.numpy()).min() > 128
    P = _prolongation(coarse)
    r = np.random.default_rng(6).standard_normal(A.shape[0])
    sums = wp.array([0.0, 0.5], dtype=wp.float64, device=device)
    coarse.restricted.fill_(7.0)  # not cleared by the caller: the restriction writes its sums
    coarse.solve(wp.array(r.reshape(-1, 3), dtype=wp.vec3d, device=device), sums, 1)
    restricted = P.T @ r
    np.testing.assert_allclose(coarse.restricted.numpy(), restricted, rtol=1e-12, atol=1e-12 * np.abs(restricted).max())
    values = coarse.inverse.numpy().astype(np.float64) @ restricted
    np.testing.assert_allclose(coarse.values.numpy(), values, rtol=1e-9, atol=1e-9 * np.abs(values).max())
    assert sums.numpy()[0] == 0.0 and sums.numpy()[1] == pytest.approx(0.5 + restricted @ values, rel=1e-9)


def _numpy_two_level_pcg(A: sp.csr_matrix, b: np.ndarray, P: sp.csr_matrix, inverse: np.ndarray,
                         iterations: int) -> np.ndarray:
    """x after ``iterations`` steps of PCG from 0 with M r = D^-1 r + P inverse P^T r (D the 3x3 diagonal blocks)."""
    blocks = diagonal_block_inverses(A)
    return pcg_iterate(A, b, lambda v: (blocks @ v.reshape(-1, 3, 1)).reshape(-1) + P @ (inverse @ (P.T @ v)),
                       iterations)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cell_mm", [3.0, 12.0])
def test_two_level_cg_iterates_are_those_of_a_numpy_pcg(device: str, cell_mm: float):
    """Stopped by its cap after 1 to 2 passes of the CG's loop and more (the sets of the state taken in turn, the
    update of r that sums P^T r, the p update that prolongs and runs the stop test), x is numpy's k-th two-level PCG
    iterate with the same (float32) coarse inverse; with 12 mm cells an aggregate has more nodes than its thread
    group has threads."""
    positions, fixed, A = _grid_system()
    H = _warp_bsr(A, device)
    coarse = CoarseSpace(positions, fixed, cell_mm, device)
    assert coarse.update(H)
    P, inverse = _prolongation(coarse), coarse.inverse.numpy().astype(np.float64)
    b = np.random.default_rng(7).standard_normal(A.shape[0]) * ~fixed.reshape(-1)
    for cap in (1, 2, 3, 4, 5, 7, 8):
        x = wp.zeros(len(positions), dtype=wp.vec3d, device=device)
        result = definite_cg(block_row_operator(H), wp.array(b.reshape(-1, 3), dtype=wp.vec3d, device=device), x,
                             1e-14, cap, BlockJacobi(H), coarse=coarse)
        assert result.iterations == cap and not result.converged, (cap, result)
        expected = _numpy_two_level_pcg(A, b, P, inverse, cap)
        np.testing.assert_allclose(x.numpy().reshape(-1), expected, rtol=1e-8, atol=1e-8 * np.abs(expected).max())


def test_aggregates_have_equal_node_counts_so_a_refined_region_gets_its_share():
    """Recursive coordinate bisection: 40 aggregates of 2,000 free nodes hold 50 +- 4 each; the refined corner (3/4 of
    the nodes in 1/64 of the volume) gets about 3/4 of the aggregates, where grid cells would give it 1/64 of them;
    each bottom node (every component fixed) joins the aggregate of its nearest free node."""
    rng = np.random.default_rng(3)
    dense = rng.uniform(0.0, 2.5, (1500, 3)) + [0.0, 0.0, 2.5]  # the corner x, y < 2.5 mm, z in [2.5, 5] mm
    sparse = rng.uniform(0.0, 10.0, (500, 3)) * [1.0, 1.0, 0.5]
    bottom = np.column_stack([rng.uniform(0.0, 10.0, (100, 2)), np.zeros(100)])
    positions = np.vstack([dense, sparse, bottom])
    fixed = np.zeros((len(positions), 3), bool)
    fixed[2000:] = True
    fixed[:10, 2] = True  # a partly fixed node is free: it is split with the others
    aggregate, count = _aggregates(positions, fixed, 40)
    assert count == 40
    sizes = np.bincount(aggregate[:2000], minlength=count)
    assert sizes.min() >= 46 and sizes.max() <= 54, sizes
    in_corner = np.bincount(aggregate[:1500], minlength=count) > 25  # aggregates mostly made of corner nodes
    assert 27 <= in_corner.sum() <= 33, in_corner.sum()
    nearest = np.argmin(np.linalg.norm(positions[2000:, None] - positions[None, :2000], axis=2), axis=1)
    np.testing.assert_array_equal(aggregate[2000:], aggregate[nearest])
    again, _ = _aggregates(positions, fixed, 40)
    np.testing.assert_array_equal(again, aggregate)
    assert _aggregates(positions[:30], fixed[:30], 40)[1] == 30  # at most one aggregate per free node


def test_coarse_inverse_inverts_live_modes_and_refuses_an_indefinite_operator():
    rng = np.random.default_rng(0)
    M = rng.standard_normal((8, 8))
    spd = M @ M.T + 8.0 * np.eye(8)
    spd[3, :] = spd[:, 3] = 0.0  # a dead mode (nothing on it)
    inverse = coarse_inverse(spd)
    live = np.arange(8) != 3
    np.testing.assert_allclose(inverse[np.ix_(live, live)] @ spd[np.ix_(live, live)], np.eye(7), atol=1e-12)
    assert np.all(inverse[3] == 0.0) and np.all(inverse[:, 3] == 0.0)
    assert coarse_inverse(np.diag([1.0, 2.0, -0.5, 1.0])) is None


@pytest.mark.parametrize("device", DEVICES)
def test_two_level_cg_solves_to_scipys_solution_in_fewer_iterations_than_block_jacobi(device: str):
    positions, fixed, A = _grid_system()
    H = _warp_bsr(A, device)
    b = np.random.default_rng(1).standard_normal(A.shape[0]) * ~fixed.reshape(-1)
    coarse = CoarseSpace(positions, fixed, 3.0, device)
    assert coarse.update(H) and coarse.ready
    exact = spla.spsolve(A.tocsc(), b)
    iterations = {}
    for name, level in (("block-Jacobi", None), ("two-level", coarse)):
        x = wp.zeros(len(positions), dtype=wp.vec3d, device=device)
        result = definite_cg(block_row_operator(H), wp.array(b.reshape(-1, 3), dtype=wp.vec3d, device=device), x,
                             1e-10, 2000, BlockJacobi(H), coarse=level)
        assert result.converged and not result.not_definite
        np.testing.assert_allclose(x.numpy().reshape(-1), exact, rtol=1e-6, atol=1e-8)
        iterations[name] = result.iterations
    assert iterations["two-level"] < 0.6 * iterations["block-Jacobi"], iterations


def test_two_level_cg_where_the_coarse_level_has_more_unknowns_than_the_mesh_has_nodes():
    """A 2 x 2 x 4 grid: 16 nodes, 3 aggregates, 18 coarse unknowns (the CG clears P^T r node by node, and here
    not one entry per node)."""
    positions, fixed, A = _grid_system((2, 2, 4))
    H = _warp_bsr(A, "cpu")
    coarse = CoarseSpace(positions, fixed, 1.0, "cpu")
    assert coarse.update(H) and coarse.size > len(positions)
    b = np.random.default_rng(2).standard_normal(A.shape[0]) * ~fixed.reshape(-1)
    x = wp.zeros(len(positions), dtype=wp.vec3d)
    result = definite_cg(block_row_operator(H), wp.array(b.reshape(-1, 3), dtype=wp.vec3d), x, 1e-12, 200,
                         BlockJacobi(H), coarse=coarse)
    assert result.converged and not result.not_definite
    np.testing.assert_allclose(x.numpy().reshape(-1), spla.spsolve(A.tocsc(), b), rtol=1e-8, atol=1e-10)
