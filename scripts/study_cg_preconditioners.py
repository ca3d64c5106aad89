"""How many CG iterations other preconditioners would take on the device CG's real Newton systems (CPU study).

    .venv/bin/python scripts/study_cg_preconditioners.py [scenes/press_slide.toml] [--frames 3] [--every 4]

Solves the scene's first frames on this CPU with the device path (``linear_solver = "cg"``: the same Newton systems as
on a GPU, up to round-off), keeps each Newton system the device CG solved (the projected Hessian H, float64, and its
right-hand side b), then solves every ``--every``-th of them again with preconditioned CG in numpy/scipy to the same
relative residual |b - H x| <= rtol |b| from x = 0 (in one go where the device CG went on from Newton's forcing term to
its tight tolerance in a second solve), with each preconditioner M below, and prints a markdown table of
the iterations and the matrix-vector products with H per iteration (what a GPU iteration costs most: BENCHMARKS.md
``fem_cg_unrolled_gpu``, 17.9 us of a 48 us iteration on an H100, the other kernels 1.3-6 us each):

- ``two-level``: the device CG's own, block-Jacobi D^-1 plus the coarse correction P A_c^-1 P^T on rigid-body modes of
  aggregates (physics/coarse_space.py); its iterations should match the device CG's (printed beside it);
- ``two-level, grid cells as aggregates``: the same count of aggregates, but the grid cells themselves, whatever their
  node counts (coarse_space.py before BENCHMARKS.md ``fem_coarse_aggregates``);
- ``two-level, N coarse unknowns``: the same with about 5 times as many aggregates (a larger dense coarse inverse);
- ``smoothed aggregation``: P smoothed once, (I - w D^-1 H) P with w = 4 / (3 lambda_max(D^-1 H)) (Vanek et al.);
- ``P1 level, exact``: D^-1 plus the P2 element's own linear (P1) subspace solved exactly, Q (Q^T H Q)^-1 Q^T with Q
  the P1-in-P2 interpolation (a bound on what a p-multigrid coarse level could give, not a practical preconditioner:
  it factorises Q^T H Q);
- ``Chebyshev(2) + coarse``: the block-Jacobi term replaced by two steps of Chebyshev iteration on D^-1 H over
  [lambda_max / 30, lambda_max] (additive; one more product);
- ``V-cycle, Chebyshev(2)``: symmetric multiplicative: Chebyshev(2) smoothing, the coarse correction on its residual,
  Chebyshev(2) smoothing again (four more products).

lambda_max(D^-1 H) comes from 20 power iterations (the Chebyshev smoothers take 1.1 times it). Products are counted per CG iteration, the CG's own
included. A study of iteration counts only: it says which preconditioner could pay on the GPU, not what it would take
there.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from unittest import mock

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import typer
from scipy.spatial import cKDTree

from transtac_sim.dataset.sequence import StageClock
from transtac_sim.physics import QuasiStaticSolver, coarse_space, device_linear
from transtac_sim.physics.host_factorisation import bsr_to_scipy
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import simulate_frames

REPO = Path(__file__).resolve().parents[1]
CHEBYSHEV_RATIO = 30.0  # the smoothers' interval: [lambda_max / this, lambda_max]


@dataclasses.dataclass
class System:
    H: sp.csr_matrix  # projected Hessian (scalar rows, 3 per node; identity on the fixed components)
    b: np.ndarray
    rtol: float
    device_iterations: int  # what the device CG took
    frame: int


def _systems(scene: Path, frames: int) -> tuple[list[System], QuasiStaticSolver]:
    """The scene's first ``frames`` frames on the CPU with the device path: each converged device CG system, and the
    solver."""
    kept: list[System] = []
    holder: dict = {}
    solve_cg, solve_step = device_linear.DeviceSolves._solve_cg, QuasiStaticSolver._solve_step

    def keeping(self, H, rhs, rtol, exact_below, coarse_from_this=True, **kwargs):
        x = solve_cg(self, H, rhs, rtol, exact_below, coarse_from_this, **kwargs)
        if x is not None and coarse_from_this:  # a Newton system (not a shifted one)
            b = rhs.numpy().reshape(-1) * (1.0 - self._fixed.numpy().reshape(-1))
            tight = kwargs.get("tight") or self.cg_tol
            if rtol > tight and exact_below > 0.0 and np.abs(x.numpy()).max() < exact_below:
                rtol = tight  # the device CG went on to its refinement's tolerance (device_linear.py ``_cg``)
            kept.append(System(bsr_to_scipy(H), b, rtol, self.last_iterations, holder["solver"].frame_index))
        return x

    def noting(self, *args, **kwargs):
        holder["solver"] = self
        return solve_step(self, *args, **kwargs)

    setup = load_setup(scene)
    physics = setup.scene.physics.model_copy(update={"device": "cpu", "linear_solver": "cg"})
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    # patch.object puts each back as it was: _solve_step is inherited (newton.py), so it is deleted from the subclass
    # again rather than left there as a copy that would hide later patches of NewtonSteps (scripts/solver_variants.py)
    with (mock.patch.object(device_linear.DeviceSolves, "_solve_cg", keeping),
          mock.patch.object(QuasiStaticSolver, "_solve_step", noting)):
        for f in simulate_frames(setup, frames, StageClock()):
            print(f"frame {f.frame}: {f.solver['iterations']} Newton iterations, {len(kept)} systems kept", flush=True)
    return kept, holder["solver"]


def _pcg(H, b, M, rtol: float, maxiter: int = 5000) -> int:
    """Preconditioned CG from 0 to |b - H x| <= rtol |b|: its iterations (-k where p . H p <= 0 at iteration k)."""
    x, r = np.zeros_like(b), b.copy()
    z = M(r)
    p, rz, tol = z.copy(), r @ z, rtol * np.linalg.norm(b)
    for k in range(1, maxiter + 1):
        q = H @ p
        pq = p @ q
        if pq <= 0.0:
            return -k
        alpha = rz / pq
        x += alpha * p
        r -= alpha * q
        if np.linalg.norm(r) <= tol:
            return k
        z = M(r)
        rz_new = r @ z
        p = z + (rz_new / rz) * p
        rz = rz_new
    return maxiter


def _diagonal_blocks(H: sp.csr_matrix, n: int) -> np.ndarray:
    """H's n 3x3 diagonal blocks (n, 3, 3)."""
    coo = H.tocoo()
    on = coo.row // 3 == coo.col // 3
    blocks = np.zeros((n, 3, 3))
    np.add.at(blocks, (coo.row[on] // 3, coo.row[on] % 3, coo.col[on] % 3), coo.data[on])
    return blocks


def _aggregate_prolongation(positions_mm, fixed, cell_mm: float, cells_factor: float = 1.0) -> sp.csr_matrix:
    """P of coarse_space.py (rigid-body modes of aggregates) with about ``cells_factor`` times its aggregates: as many
    as cells of cell_mm / cells_factor^(1/3), at most cells_factor x sqrt(nodes) of them."""
    counts = coarse_space._cell_counts
    coarse_space._cell_counts = lambda extent, cell, nodes: counts(extent, cell, int(cells_factor ** 2 * nodes))
    try:
        aggregate, arm, count = coarse_space._modes(positions_mm, fixed, cell_mm / cells_factor ** (1 / 3))
    finally:
        coarse_space._cell_counts = counts
    return _prolongation(aggregate, coarse_space.basis_matrices(arm, fixed), count)


def _grid_cell_aggregates(positions_mm, cell_mm: float) -> tuple[np.ndarray, int]:
    """(aggregate of each node, aggregates) as coarse_space.py had them before ``fem_coarse_aggregates``: the grid cells
    themselves (as many as coarse_space.py makes, over the nodes' bounding box), whatever their node counts."""
    lo, hi = positions_mm.min(axis=0), positions_mm.max(axis=0)
    cells = coarse_space._cell_counts(hi - lo, cell_mm, len(positions_mm))
    size = np.where(hi > lo, (hi - lo) / cells, 1.0)
    index = np.minimum(np.floor((positions_mm - lo) / size).astype(int), cells - 1)
    _, aggregate = np.unique((index[:, 0] * cells[1] + index[:, 1]) * cells[2] + index[:, 2], return_inverse=True)
    return aggregate.reshape(-1), int(aggregate.max()) + 1


def _grid_cell_prolongation(positions_mm, fixed, cell_mm: float) -> sp.csr_matrix:
    """P with the grid cells as aggregates (``_grid_cell_aggregates``)."""
    aggregate, count = _grid_cell_aggregates(positions_mm, cell_mm)
    arm = coarse_space.rigid_modes(positions_mm, fixed, aggregate, count)
    return _prolongation(aggregate, coarse_space.basis_matrices(arm, fixed), count)


def _free_nodes_per_aggregate(aggregate: np.ndarray, count: int, fixed: np.ndarray) -> str:
    """"min / median / max" of the free nodes in each aggregate."""
    sizes = np.bincount(aggregate[~fixed.all(axis=1)], minlength=count)
    return f"{sizes.min()} / {np.median(sizes):g} / {sizes.max()}"


def _prolongation(aggregate: np.ndarray, basis: np.ndarray, count: int) -> sp.csr_matrix:
    """P (3 nodes x 6 aggregates) from each node's aggregate and its B_i (n, 3, 6)."""
    n = len(aggregate)
    rows = np.repeat(3 * np.arange(n)[:, None] + np.arange(3), 6, axis=1).reshape(n, 3, 6)
    cols = np.broadcast_to((6 * aggregate[:, None] + np.arange(6))[:, None, :], (n, 3, 6))
    return sp.csr_matrix((basis.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * n, 6 * count))


def _p1_prolongation(solver: QuasiStaticSolver) -> sp.csr_matrix:
    """Q: the P1 field of the mesh's vertices interpolated at the P2 nodes (a vertex node its vertex, an edge node the
    mean of its edge's two), 0 on the fixed components."""
    V, T = solver.vertices_mm, solver.tets
    nodes = solver._node_positions.numpy()
    edges = np.unique(np.sort(T[:, [0, 1, 0, 2, 0, 3, 1, 2, 1, 3, 2, 3]].reshape(-1, 2), axis=1), axis=0)
    _, node_of_edge = cKDTree(nodes).query(0.5 * (V[edges[:, 0]] + V[edges[:, 1]]))
    rows = np.concatenate([solver._node_of_vertex, node_of_edge, node_of_edge])
    cols = np.concatenate([np.arange(len(V)), edges[:, 0], edges[:, 1]])
    values = np.concatenate([np.ones(len(V)), np.full(2 * len(edges), 0.5)])
    S = sp.csr_matrix((values, (rows, cols)), shape=(len(nodes), len(V)))
    return sp.diags(1.0 - solver._fixed_nodes.reshape(-1).astype(float)) @ sp.kron(S, sp.identity(3), format="csr")


def _coarse_solver(H, P):
    """r -> P A_c^-1 P^T r with A_c = P^T H P (dead modes left out as coarse_space.coarse_inverse does)."""
    inverse = coarse_space.coarse_inverse((P.T @ (H @ P)).toarray())
    if inverse is None:
        raise RuntimeError("the Galerkin operator is not positive definite")
    return lambda r: P @ (inverse @ (P.T @ r))


def _chebyshev(H, D_inv, r, steps: int, lambda_max: float) -> np.ndarray:
    """``steps`` steps of Chebyshev iteration on D^-1 H x = D^-1 r from 0 over [lambda_max / CHEBYSHEV_RATIO,
    lambda_max] (Saad, Iterative Methods, Algorithm 12.1)."""
    low = lambda_max / CHEBYSHEV_RATIO
    theta, delta = 0.5 * (lambda_max + low), 0.5 * (lambda_max - low)
    sigma = theta / delta
    rho = 1.0 / sigma
    residual = D_inv @ r
    d = residual / theta
    x = d.copy()
    for _ in range(steps - 1):
        residual = residual - D_inv @ (H @ d)
        rho_next = 1.0 / (2.0 * sigma - rho)
        d = rho_next * rho * d + (2.0 * rho_next / delta) * residual
        x += d
        rho = rho_next
    return x


def _lambda_max(H, D_inv, free: np.ndarray) -> float:
    """lambda_max(D^-1 H) by 20 power iterations (from below)."""
    x = np.random.default_rng(0).standard_normal(H.shape[0]) * free
    value = 1.0
    for _ in range(20):
        x = D_inv @ (H @ x)
        value = np.linalg.norm(x)
        x /= value
    return value


def _preconditioners(s: System, solver: QuasiStaticSolver) -> dict:
    """name -> (M, matrix-vector products with H per CG iteration, the CG's own included)."""
    H = s.H
    fixed = solver._fixed_nodes
    positions = solver._node_positions.numpy()
    cell_mm = solver.settings.coarse_cell_mm
    n = H.shape[0] // 3
    D_inv = sp.bsr_matrix((np.linalg.inv(_diagonal_blocks(H, n)), np.arange(n), np.arange(n + 1)), shape=H.shape).tocsr()
    free = 1.0 - fixed.reshape(-1).astype(float)
    lam = _lambda_max(H, D_inv, free)
    P = _aggregate_prolongation(positions, fixed, cell_mm)
    coarse = _coarse_solver(H, P)
    grid = _coarse_solver(H, _grid_cell_prolongation(positions, fixed, cell_mm))
    P6 = _aggregate_prolongation(positions, fixed, cell_mm, 6.0)
    coarse6 = _coarse_solver(H, P6)
    smoothed = _coarse_solver(H, (P - (4.0 / (3.0 * lam)) * (D_inv @ (H @ P))).tocsr())
    bound = 1.1 * lam  # the Chebyshev smoothers' upper end: above the power iteration's estimate
    Q = _p1_prolongation(solver)
    A1 = Q.T @ H @ Q
    A1 = (A1 + sp.diags((A1.diagonal() == 0.0).astype(float))).tocsc()  # the fixed vertices' rows and columns
    p1 = sla.splu(A1)

    def v_cycle(r):
        x = _chebyshev(H, D_inv, r, 2, bound)
        x = x + coarse(r - H @ x)
        return x + _chebyshev(H, D_inv, r - H @ x, 2, bound)

    return {f"two-level (the device CG's; {P.shape[1]} coarse unknowns)": (lambda r: D_inv @ r + coarse(r), 1),
            "two-level, grid cells as aggregates": (lambda r: D_inv @ r + grid(r), 1),
            f"two-level, {P6.shape[1]} coarse unknowns": (lambda r: D_inv @ r + coarse6(r), 1),
            "smoothed aggregation": (lambda r: D_inv @ r + smoothed(r), 1),
            "P1 level, exact": (lambda r: D_inv @ r + Q @ p1.solve(Q.T @ r), 1),
            "Chebyshev(2) + coarse": (lambda r: _chebyshev(H, D_inv, r, 2, bound) + coarse(r), 2),
            "V-cycle, Chebyshev(2)": (v_cycle, 5)}


def main(scene: Path = typer.Argument(REPO / "scenes" / "press_slide.toml"), frames: int = typer.Option(3, min=1),
         every: int = typer.Option(4, min=1, help="study every this-th Newton system")) -> None:
    systems, solver = _systems(scene, frames)
    if solver.settings.coarse_cell_mm is None:
        raise typer.BadParameter("the scene has no coarse level ([physics] coarse_cell_mm); this study compares with it")
    chosen = systems[::every]
    rows = []
    for i, s in enumerate(chosen):
        found = {name: (_pcg(s.H, s.b, M, s.rtol), products) for name, (M, products) in _preconditioners(s, solver).items()}
        rows.append((s, found))
        print(f"system {i + 1} of {len(chosen)} (frame {s.frame}): "
              + ", ".join(f"{name} {its}" for name, (its, _) in found.items()), flush=True)
    names = list(rows[0][1])
    positions, fixed = solver._node_positions.numpy(), solver._fixed_nodes
    aggregate, count = coarse_space._modes(positions, fixed, solver.settings.coarse_cell_mm)[::2]
    print(f"\n{scene}, frames 0-{frames - 1} on the CPU (device path), {len(systems)} Newton systems, every {every}-th "
          f"studied; {len(positions)} P2 nodes, {count} aggregates holding min / median / max free nodes "
          f"{_free_nodes_per_aggregate(aggregate, count, fixed)} (as grid cells: "
          f"{_free_nodes_per_aggregate(*_grid_cell_aggregates(positions, solver.settings.coarse_cell_mm), fixed)}). "
          "CG iterations to each system's rtol (negative: stopped at p . H p <= 0), products with H per iteration in "
          "the header:\n")
    print("| frame | rtol | device CG | " + " | ".join(f"{n} ({rows[0][1][n][1]})" for n in names) + " |")
    print("|---|---|---|" + "---|" * len(names))
    for s, found in rows:
        print(f"| {s.frame} | {s.rtol:.1e} | {s.device_iterations} | " + " | ".join(str(found[n][0]) for n in names) + " |")
    totals = {n: sum(abs(found[n][0]) for _, found in rows) for n in names}
    base = totals[names[0]]
    print("| all | | " + str(sum(s.device_iterations for s, _ in rows)) + " | "
          + " | ".join(f"{totals[n]} ({totals[n] / base:.2f}x)" for n in names) + " |")


if __name__ == "__main__":
    typer.run(main)
