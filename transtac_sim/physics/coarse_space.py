"""The coarse level of the device CG's two-level preconditioner: rigid-body modes of aggregates of nodes.

Block-Jacobi alone (definite_cg.py) removes only what is local to a node; the slowly varying part of the error, which
spans the whole gel, takes CG many iterations to spread (150-500 per Newton system on press_slide,
BENCHMARKS.md ``fem_slide_iterations_gpu``). The coarse level solves for that part directly. The free nodes are split
into aggregates of equal node counts by recursive coordinate bisection (``_aggregates``), as many as the gel's bounding
box has grid cells of about ``cell_mm`` (at most sqrt(nodes), ``_cell_counts``), so that on a mesh refined under the
contact more of them lie there: on press_slide's Newton systems 0.82x the CG iterations of the grid cells themselves
as aggregates (a CPU study), and the device CG 0.87-0.91x per solve on an H100 (BENCHMARKS.md
``fem_coarse_aggregates``). Each aggregate a carries six coarse unknowns, a translation t_a and a small rotation w_a
(mm, rad). The prolongation P maps them to the nodes:

    (P y)_i = f_i o (t_a + w_a x c_i) = B_i y_a,      B_i = diag(f_i) [ I | -[c_i]x ]   (3 x 6),

with a the aggregate of node i, c_i = X_i - (the centroid of a's free nodes) (mm), and f_i the node's free mask (0 on
the bonded components, which stay 0). An aggregate with fewer than 4 free nodes, or whose free nodes lie near a line,
keeps its translations only (its rotations are not independent there). The additive two-level preconditioner
(Toselli & Widlund 2005, ch. 2) is

    M r = D^-1 r + P A_c^-1 P^T r,      A_c = P^T H P (the Galerkin operator, m x m, m = 6 x aggregates),

symmetric positive definite wherever D and A_c are. (P^T r)_a = sum over a's nodes of B_i^T r_i = (sum f_i o r_i,
sum c_i x (f_i o r_i)). The device keeps B_i as its two vectors c_i and f_i (``arm``, ``free``: 48 instead of 144 bytes
a node, read at every CG iteration) and the nodes in order of their aggregate (``members``, ``starts``), so that one
thread group sums an aggregate's part of P^T r without atomics. ``update`` forms A_c on the device (one thread per
block row, its blocks' B_i^T H_ij B_j added atomically into a dense matrix) and inverts it on the host (Cholesky;
LAPACK ``potrf``/``potri``): about 1,000 unknowns on the default gel with cell_mm = 3. The CG applies it on the device
(definite_cg.py, its kernels in cg_kernels.py): P^T r where it updates r, then the inverse as a dense float32 product
that also adds the coarse part of r . M r, (P^T r) . A_c^-1 P^T r (``apply_inverse``); P A_c^-1 P^T r is added where the
CG updates p. On press_slide (H100) a CG iteration costs 1.7x and a Newton system takes 0.43x the iterations: the CG
0.7x the time, the frames 1.22-1.35x faster (BENCHMARKS.md ``fem_coarse_level_gpu``). Modes that carry nothing (an
aggregate whose nodes are all fixed, rotations left out) are dropped from the inverse. Where A_c is not positive
definite (H is not), ``update`` keeps the last inverse: any positive definite A_c^-1 gives a positive definite M, and
one made from an earlier Newton system of the same gel still captures its rigid motions.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp
from scipy.linalg import lapack
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from transtac_sim.physics.sparse_product import block_row_range

vec6d = wp.types.vector(length=6, dtype=wp.float64)

#: an aggregate keeps its rotations where its free nodes' second moment about their centroid has its smallest
#: eigenvalue above this fraction of its largest (nodes near a line have a rotation that moves none of them)
ROTATION_SPREAD = 1.0e-3
#: threads per group of an aggregate's nodes (the restriction, cg_kernels.py's update of r) and per row of the coarse
#: product (more than one warp per row: the coarse matrix has about 1,000 rows, too few warps of one row each to keep
#: the memory busy)
AGGREGATE_THREADS = wp.constant(128)
PRODUCT_THREADS = 128
#: coarse modes whose Galerkin diagonal is below this fraction of the largest carry nothing and are dropped
DEAD_MODE = 1.0e-12


@wp.func
def mode_basis(arm: wp.vec3d, free: wp.vec3d):
    """B_i = diag(f_i) [ I | -[c_i]x ] (3 x 6) of a node's ``arm`` c_i and ``free`` mask f_i."""
    return wp.diag(free) * wp.matrix_from_rows(
        vec6d(wp.float64(1.0), wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), arm[2], -arm[1]),
        vec6d(wp.float64(0.0), wp.float64(1.0), wp.float64(0.0), -arm[2], wp.float64(0.0), arm[0]),
        vec6d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0), arm[1], -arm[0], wp.float64(0.0)))


@wp.func
def restrict_node(arm: wp.vec3d, free: wp.vec3d, r: wp.vec3d):
    """B_i^T r_i = (f_i o r_i, c_i x (f_i o r_i)): a node's part of P^T r."""
    fr = wp.cw_mul(free, r)
    w = wp.cross(arm, fr)
    return vec6d(fr[0], fr[1], fr[2], w[0], w[1], w[2])


@wp.func
def prolong(arm: wp.array(dtype=wp.vec3d), free: wp.array(dtype=wp.vec3d), aggregate: wp.array(dtype=int),
            values: wp.array(dtype=wp.float64), i: int):
    """(P y)_i = B_i y_a = f_i o (t_a + w_a x c_i) for the coarse values y (a node i's aggregate)."""
    a = 6 * aggregate[i]
    t = wp.vec3d(values[a], values[a + 1], values[a + 2])
    w = wp.vec3d(values[a + 3], values[a + 4], values[a + 5])
    return wp.cw_mul(free[i], t + wp.cross(w, arm[i]))


@wp.func
def group_range(starts: wp.array(dtype=int), group: int, count: int):
    """Positions [start, end) of thread group ``group``'s nodes: an aggregate's (``starts``, into ``members``) or, with
    ``starts`` empty, ``AGGREGATE_THREADS`` consecutive nodes of ``count`` (on the CPU a group is one thread)."""
    if starts.shape[0] > 0:
        return wp.vec2i(starts[group], starts[group + 1])
    start = group * AGGREGATE_THREADS
    return wp.vec2i(start, wp.min(start + AGGREGATE_THREADS, count))


@wp.kernel(enable_backward=False)
def _galerkin(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
              blocks: wp.array(dtype=wp.mat33d), arm: wp.array(dtype=wp.vec3d), free: wp.array(dtype=wp.vec3d),
              aggregate: wp.array(dtype=int), coarse: wp.array2d(dtype=wp.float64)):
    """coarse[6a:6a+6, 6b:6b+6] += B_i^T H_ij B_j over block row i's blocks (a, b the aggregates of i and j)."""
    row = wp.tid()
    blocks_of_row = block_row_range(offsets, row_counts, row)
    left = wp.transpose(mode_basis(arm[row], free[row]))
    a = 6 * aggregate[row]
    for k in range(blocks_of_row[0], blocks_of_row[1]):
        col = columns[k]
        product = left * (blocks[k] * mode_basis(arm[col], free[col]))
        b = 6 * aggregate[col]
        for r in range(6):
            for c in range(6):
                wp.atomic_add(coarse, a + r, b + c, product[r, c])


@wp.kernel(enable_backward=False)
def _restrict(r: wp.array(dtype=wp.vec3d), arm: wp.array(dtype=wp.vec3d), free: wp.array(dtype=wp.vec3d),
              members: wp.array(dtype=int), starts: wp.array(dtype=int), restricted: wp.array(dtype=wp.float64)):
    """restricted[6a:6a+6] = sum of B_i^T r_i over aggregate a's nodes: one thread group per aggregate, a tile sum."""
    a, lane = wp.tid()
    nodes = group_range(starts, a, members.shape[0])
    part = vec6d()
    for k in range(nodes[0] + lane, nodes[1], wp.block_dim()):
        i = members[k]
        part += restrict_node(arm[i], free[i], r[i])
    total = wp.tile_sum(wp.tile(part, preserve_type=True))
    if lane == 0:
        for c in range(6):
            restricted[6 * a + c] = total[0][c]


@wp.kernel(enable_backward=False)
def _coarse_product(inverse: wp.array2d(dtype=wp.float32), x: wp.array(dtype=wp.float64),
                    y: wp.array(dtype=wp.float64), sums: wp.array(dtype=wp.float64), slot: int):
    """y = inverse x, and x . y added to sums[slot]: one thread group per row, its lanes striding over the row
    (coalesced), then a tile sum."""
    row, lane = wp.tid()
    partial = wp.float64(0.0)
    for j in range(lane, x.shape[0], wp.block_dim()):
        partial += wp.float64(inverse[row, j]) * x[j]
    total = wp.tile_sum(wp.tile(partial))
    if lane == 0:
        y[row] = total[0]
        wp.atomic_add(sums, slot, x[row] * total[0])


def _aggregates(positions_mm: np.ndarray, fixed: np.ndarray, count: int) -> tuple[np.ndarray, int]:
    """(aggregate of each node, aggregates): the free nodes (those with a free component) split into min(``count``,
    free nodes) parts whose sizes differ by at most a few nodes, by recursive coordinate bisection: a part of k
    aggregates is cut across its longest extent so that each side holds its share of nodes for k // 2 and k - k // 2
    aggregates. A node with every component fixed joins its nearest free node's aggregate (its B_i is 0 either way)."""
    free = np.flatnonzero(~fixed.all(axis=1))
    aggregate = np.zeros(len(positions_mm), dtype=int)
    if len(free) == 0:
        return aggregate, 1
    parts, made = [(free, min(count, len(free)))], 0
    while parts:
        nodes, k = parts.pop()
        if k == 1:
            aggregate[nodes] = made
            made += 1
            continue
        p = positions_mm[nodes]
        order = nodes[np.argsort(p[:, np.argmax(np.ptp(p, axis=0))], kind="stable")]
        low = k // 2
        cut = int(round(len(order) * low / k))  # >= low nodes on one side, >= k - low on the other: len(order) >= k
        parts += [(order[cut:], k - low), (order[:cut], low)]
    held = np.flatnonzero(fixed.all(axis=1))
    if len(held):
        aggregate[held] = aggregate[free[cKDTree(positions_mm[free]).query(positions_mm[held])[1]]]
    return aggregate, made


def _modes(positions_mm: np.ndarray, fixed: np.ndarray, cell_mm: float) -> tuple[np.ndarray, np.ndarray, int]:
    """(aggregate of each node, each node's arm c_i (n, 3), aggregates): ``_aggregates``, as many as the nodes'
    bounding box has grid cells of about ``cell_mm``, or fewer where that would be more than sqrt(nodes)
    (``_cell_counts``); ``rigid_modes``."""
    cells = _cell_counts(positions_mm.max(axis=0) - positions_mm.min(axis=0), cell_mm, len(positions_mm))
    aggregate, count = _aggregates(positions_mm, fixed, int(cells.prod()))
    return aggregate, rigid_modes(positions_mm, fixed, aggregate, count), count


def rigid_modes(positions_mm: np.ndarray, fixed: np.ndarray, aggregate: np.ndarray, count: int) -> np.ndarray:
    """Each node's arm c_i (n, 3; mm) for the aggregates ``aggregate`` (of each node, ``count`` of them): its offset
    from its aggregate's free nodes' centroid, 0 where the aggregate keeps its translations only (fewer than 4 free
    nodes, or nodes near a line, ``ROTATION_SPREAD``). With the free mask f_i (``~fixed``) it gives B_i
    (``basis_matrices``)."""
    free_node = ~fixed.all(axis=1)
    members = np.bincount(aggregate[free_node], minlength=count)
    centroid = np.zeros((count, 3))
    np.add.at(centroid, aggregate[free_node], positions_mm[free_node])
    centroid /= np.maximum(members, 1)[:, None]
    c = positions_mm - centroid[aggregate]
    moment = np.zeros((count, 3, 3))
    np.add.at(moment, aggregate[free_node], c[free_node, :, None] * c[free_node, None, :])
    spread = np.linalg.eigvalsh(moment)
    rotations = (members >= 4) & (spread[:, 0] > ROTATION_SPREAD * np.maximum(spread[:, 2], 1e-300))
    return c * rotations[aggregate][:, None]


def basis_matrices(arm: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """B_i (n, 3, 6) = diag(f_i) [ I | -[c_i]x ] of the arms c_i (n, 3) and the fixed components (bool (n, 3); f_i is
    1 where free): column 3 + k is e_k x c_i."""
    basis = np.zeros((len(arm), 3, 6))
    basis[:, :, :3] = np.eye(3)
    x, y, z = arm.T
    zero = np.zeros_like(x)
    basis[:, :, 3] = np.stack([zero, -z, y], axis=1)  # w = e_x: e_x x c
    basis[:, :, 4] = np.stack([z, zero, -x], axis=1)  # e_y x c
    basis[:, :, 5] = np.stack([-y, x, zero], axis=1)  # e_z x c
    return basis * (~fixed)[:, :, None]


def _cell_counts(extent_mm: np.ndarray, cell_mm: float, nodes: int) -> np.ndarray:
    """Cells along each axis: about ``cell_mm`` each, grown by 10 % steps until there are at most sqrt(nodes) of them.
    The CG's dense coarse product costs (6 cells)^2 per iteration against about 250 nodes for its sparse product: at
    sqrt(nodes) cells the coarse one is at most a sixth of it (the default gel: 176 cells of 3 mm for 31k P2 nodes)."""
    while True:
        cells = np.maximum(1, np.round(extent_mm / cell_mm)).astype(int)
        if cells.prod() <= max(1.0, np.sqrt(nodes)):
            return cells
        cell_mm *= 1.1


def coarse_inverse(galerkin: np.ndarray) -> np.ndarray | None:
    """The inverse of the Galerkin operator (m x m, float64) over its live modes (0 on the dead ones, ``DEAD_MODE``),
    or None where it is not positive definite."""
    diagonal = np.diag(galerkin)
    dead = np.abs(diagonal) <= DEAD_MODE * float(np.abs(diagonal).max())
    a = galerkin.copy()
    a[dead, :] = 0.0
    a[:, dead] = 0.0
    a[dead, dead] = 1.0
    a = 0.5 * (a + a.T)
    factor, info = lapack.dpotrf(a, lower=1, clean=1)
    if info != 0:
        return None
    inverse, info = lapack.dpotri(factor, lower=1)
    if info != 0:
        return None
    inverse = np.tril(inverse) + np.tril(inverse, -1).T
    inverse[dead, :] = 0.0
    inverse[:, dead] = 0.0
    return inverse


class CoarseSpace:
    """The aggregates' rigid-body modes of a solver's nodes (``positions_mm`` (n, 3), ``fixed`` bool (n, 3)) on
    ``device``, with the kept coarse inverse (``ready`` once ``update`` has made one) and the CG's coarse vectors.
    Arrays keep their addresses between updates, so a CUDA graph captured with them stays valid."""

    def __init__(self, positions_mm: np.ndarray, fixed: np.ndarray, cell_mm: float, device):
        if not cell_mm > 0.0:
            raise ValueError(f"coarse cell size must be > 0 mm, got {cell_mm}")
        fixed = np.asarray(fixed, bool)
        aggregate, arm, count = _modes(np.asarray(positions_mm, dtype=np.float64), fixed, cell_mm)
        self.device = device
        self.size = 6 * count  # coarse unknowns
        self.aggregate = wp.array(aggregate.astype(np.int32), dtype=int, device=device)
        order = np.argsort(aggregate, kind="stable")  # the nodes of each aggregate, one after another
        self.members = wp.array(order.astype(np.int32), dtype=int, device=device)
        starts = np.concatenate([[0], np.cumsum(np.bincount(aggregate, minlength=count))])
        self.starts = wp.array(starts.astype(np.int32), dtype=int, device=device)  # aggregate a: members[starts[a]:]
        self.arm = wp.array(arm, dtype=wp.vec3d, device=device)  # c_i (mm), 0 where the aggregate has no rotations
        self.free = wp.array((~fixed).astype(np.float64), dtype=wp.vec3d, device=device)  # f_i
        self.inverse = wp.zeros((self.size, self.size), dtype=wp.float32, device=device)
        self.restricted = wp.zeros(self.size, dtype=wp.float64, device=device)  # P^T r
        self.values = wp.zeros(self.size, dtype=wp.float64, device=device)  # A_c^-1 P^T r
        self._galerkin = wp.zeros((self.size, self.size), dtype=wp.float64, device=device)
        self.ready = False
        self.updates = 0  # coarse inverses made
        self.rejected = 0  # Galerkin operators found not positive definite (the last inverse kept)
        self.seconds = {"galerkin": 0.0, "inverse": 0.0}  # ``update``'s time: A_c on the device, its inverse on the host

    @property
    def aggregates(self) -> int:
        """The aggregates (six coarse unknowns each)."""
        return self.size // 6

    def galerkin(self, H) -> np.ndarray:
        """A_c = P^T H P (m x m, float64, on the host) for a 3x3-block BSR matrix H on the device."""
        self._galerkin.zero_()
        wp.launch(_galerkin, dim=H.nrow, device=self.device,
                  inputs=[H.offsets, H.row_counts, H.columns, H.values, self.arm, self.free, self.aggregate,
                          self._galerkin])
        return self._galerkin.numpy()

    def update(self, H) -> bool:
        """Makes the coarse inverse from H's Galerkin operator; False (the last one kept) where that is not positive
        definite."""
        start = time.perf_counter()
        galerkin = self.galerkin(H)
        middle = time.perf_counter()
        with threadpool_limits(limits=1, user_api="blas"):  # BLAS threads left spinning slow other workers (linear.py)
            inverse = coarse_inverse(galerkin)
        self.seconds["galerkin"] += middle - start
        self.seconds["inverse"] += time.perf_counter() - middle
        if inverse is None:
            self.rejected += 1
            return False
        self.inverse.assign(inverse.astype(np.float32))
        self.ready = True
        self.updates += 1
        return True

    def apply_inverse(self, sums: wp.array, slot: int) -> None:
        """values = A_c^-1 restricted, and restricted . values (= r . P values, the coarse part of the CG's r . M r)
        added to sums[slot]; graph-capturable (one launch)."""
        wp.launch_tiled(_coarse_product, dim=[self.size], block_dim=PRODUCT_THREADS, device=self.device,
                        inputs=[self.inverse, self.restricted, self.values, sums, slot])

    def solve(self, r: wp.array, sums: wp.array, slot: int) -> None:
        """values = A_c^-1 P^T r (P^T r into ``restricted`` first), as ``apply_inverse``; graph-capturable (two
        launches). The CG forms P^T r in its own update of r instead (cg_kernels.py ``_step_precondition``)."""
        wp.launch_tiled(_restrict, dim=[self.aggregates], block_dim=AGGREGATE_THREADS, device=self.device,
                        inputs=[r, self.arm, self.free, self.members, self.starts, self.restricted])
        self.apply_inverse(sums, slot)
