"""Preconditioned conjugate gradients on the solver's device that stop where the matrix is not positive definite.

Newton's exact Hessian (elasticity.py) is indefinite far from equilibrium (in compression its volumetric term's
twist/flip eigenvalues mu + s sigma_k are negative at nearly every tet), and positive definite near it. The host
path learns which from CHOLMOD and takes the clamped Hessian only where needed (newton.py ``_hessian_ladder``);
Warp's ``cg`` cannot tell: on an indefinite system it runs to its iteration cap (BENCHMARKS.md
``fem_newton_variants_gpu``: trying the exact Hessian that way cost more CG iterations than it saved Newton ones).
This CG (Nocedal & Wright, Algorithm 5.3, with the curvature test of Algorithm 7.1) stops at the first sign:

    r = b - A x,  z = M r,  p = z
    repeat:  q = A p,  c = p . q             c <= 0: A is not positive definite along p  -> stop
             alpha = (r . z) / c,  x += alpha p,  r -= alpha q
             z = M r                         r . z <= 0: neither is the preconditioner   -> stop
             p = z + (r . z)_new / (r . z) p
    until |r| <= tol (= max(rtol |b|, atol)) or ``maxiter`` iterations.

M is block-Jacobi (``BlockJacobi``: the inverses of the 3x3 diagonal blocks), block-Jacobi plus a coarse correction on
rigid-body modes of aggregates of nodes (``coarse``: coarse_space.py), or none. It runs on the device like
``warp.optim.linear.cg``, but with conditional CUDA graphs (CUDA 12.4+) the whole solve is one graph: the start (r, z,
p, |b|^2, then the tolerance and the stop tests before the first iteration, ``_start``), the loop
(``wp.capture_while``) and max |x| at the end (reductions.py, copied into the state). The host writes only the
solve's tolerances and cap before it (``_set_limits``) and reads the state once, at the end; without conditional
graphs one iteration is captured and launched ``CHECK_EVERY`` times between host reads. An iteration is five
launches: the product, p . q, then one kernel for the updates of x and r, z = M r, r . z and |r|^2 (all per
entry), with the coarse level two more (P^T r, then A_c^-1 P^T r and its part of r . z), the update of p (which adds
the coarse part of z), and the stop test. The state (r . z, p . q, |r|^2, tolerance, stop reason, iteration,
whether it is still going, iteration cap, and at the end max |x|, its NaN count and x . b) is one small float64 array,
so the iterations of a stopped solve change nothing (x, r and p keep their values). A pass of the captured loop
therefore runs ``UNROLL`` iterations, and a solve pays for at most UNROLL - 1 iterations after its stop: on
press_slide's Newton system (H100) 4 iterations a pass took 0.93-0.96x the time of 1
(BENCHMARKS.md ``fem_cg_unrolled_gpu``, scripts/bench_cg_kernels.py). Dot products are block-wise tile sums
added atomically (round-off varies from run to run in the last bits, as the assembly's atomics already do).

A ``CgWorkspace`` keeps the work vectors (b copied into its own), the state and the last captured graph between solves
of one size (a solver's Newton systems): a solve whose arrays are those of an earlier one (the operator's ``graph_key``,
the preconditioner and x) launches that solve's graph instead of capturing and instantiating its own (press_slide on an
H100: one graph for all its frames, 0.87x the CG's time per solve; BENCHMARKS.md ``fem_cg_kept_graphs_gpu``). The state
is cleared at the start of every solve. Before the start moved into the graph, a solve read the state twice, and the
GPU waited between the two reads while the host wrote the state of the first iteration and launched the loop
(scripts/fem_host_census.py; BENCHMARKS.md ``fem_host_census_gpu``).
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp
from warp.optim.linear import LinearOperator
from warp.sparse import BsrMatrix

from transtac_sim.physics.coarse_space import CoarseSpace, mat36d, prolong
from transtac_sim.physics.reductions import launch_max_abs, reduction_buffer
from transtac_sim.physics.sparse_product import diagonal_block

CHECK_EVERY = 8  # host path without conditional graphs: iterations between reads of the state
UNROLL = 4  # iterations per pass of the conditional graph's loop (CUDA)
DOT_BLOCKS = 256  # thread blocks of a dot product (each strides over the vector)
DOT_THREADS = 256

# the state array's slots (X_MAX, X_NANS: max |x| over entries and components at the end, and the entries with a NaN;
# XB: x . b at the end)
RZ, RZ_NEW, PQ, RR, TOL2, STOP, ITER, ACTIVE, MAXITER, X_MAX, X_NANS, XB = (wp.constant(k) for k in range(12))
STATE_SIZE = 12
# why it stopped (the STOP slot)
_STOPS = (1.0, 2.0, 3.0, 4.0)
CONVERGED, NOT_DEFINITE, PRECONDITIONER_NOT_DEFINITE, ITERATION_CAP = (wp.constant(wp.float64(k)) for k in _STOPS)


@dataclass(frozen=True)
class CgResult:
    converged: bool
    not_definite: bool  # stopped at p . A p <= 0 (or r . M r <= 0): the matrix (or M) is not positive definite
    iterations: int
    x_max: float  # max |x| over its entries and components at the end (NaN where an entry is NaN)
    x_dot_b: float  # x . b at the end (Newton's slope along its step, with b = -g: newton.py)


@wp.kernel(enable_backward=False)
def _inverse_diagonal(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                      blocks: wp.array(dtype=wp.mat33d), inverse: wp.array(dtype=wp.mat33d)):
    row = wp.tid()
    k = diagonal_block(offsets, row_counts, columns, row)
    if k >= 0:
        inverse[row] = wp.inverse(blocks[k])
    else:  # a row without a diagonal block: not preconditioned
        inverse[row] = wp.identity(n=3, dtype=wp.float64)


@wp.kernel(enable_backward=False)
def _apply_blocks(inverse: wp.array(dtype=wp.mat33d), x: wp.array(dtype=wp.vec3d), y: wp.array(dtype=wp.vec3d),
                  z: wp.array(dtype=wp.vec3d), alpha: wp.float64, beta: wp.float64):
    i = wp.tid()
    value = alpha * (inverse[i] * x[i])
    if beta != wp.float64(0.0):
        value += beta * y[i]
    z[i] = value


class BlockJacobi(LinearOperator):
    """The block-Jacobi preconditioner of a 3x3-block matrix: the inverses of its diagonal blocks
    (``inverse_blocks``, written into ``inverse`` where given), usable as a ``warp.optim.linear`` operator too."""

    def __init__(self, A: BsrMatrix, inverse: wp.array | None = None):
        self.inverse_blocks = inverse if inverse is not None else wp.empty(A.nrow, dtype=wp.mat33d, device=A.device)
        wp.launch(_inverse_diagonal, dim=A.nrow, device=A.device,
                  inputs=[A.offsets, A.row_counts, A.columns, A.values, self.inverse_blocks])

        def matvec(x, y, z, alpha, beta):
            wp.launch(_apply_blocks, dim=A.nrow, device=A.device,
                      inputs=[self.inverse_blocks, x, y, z, wp.float64(alpha), wp.float64(beta)])

        super().__init__(A.shape, A.scalar_type, A.device, matvec)


@wp.kernel(enable_backward=False)
def _dot(a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d), state: wp.array(dtype=wp.float64), slot: int,
         blocks: int):
    block, lane = wp.tid()
    partial = wp.float64(0.0)
    for i in range(block * wp.block_dim() + lane, a.shape[0], blocks * wp.block_dim()):
        partial += wp.dot(a[i], b[i])
    total = wp.tile_sum(wp.tile(partial))
    if lane == 0:
        wp.atomic_add(state, slot, total[0])


@wp.kernel(enable_backward=False)
def _step_precondition(state: wp.array(dtype=wp.float64), p: wp.array(dtype=wp.vec3d), q: wp.array(dtype=wp.vec3d),
                       inverse: wp.array(dtype=wp.mat33d), precondition: int, x: wp.array(dtype=wp.vec3d),
                       r: wp.array(dtype=wp.vec3d), z: wp.array(dtype=wp.vec3d), blocks: int):
    """x += alpha p, r -= alpha q (alpha = r.z / p.q), z = M r (block-Jacobi), and the sums r . z -> RZ_NEW,
    |r|^2 -> RR. With a coarse level its part of z is added where p is updated (``_step_p``) and its part of r . z,
    (P^T r) . (A_c^-1 P^T r), by the coarse product (coarse_space.py)."""
    block, lane = wp.tid()
    step = state[ACTIVE] != wp.float64(0.0) and state[PQ] > wp.float64(0.0)
    alpha = wp.float64(0.0)
    if step:
        alpha = state[RZ] / state[PQ]
    rz = wp.float64(0.0)
    rr = wp.float64(0.0)
    for i in range(block * wp.block_dim() + lane, x.shape[0], blocks * wp.block_dim()):
        ri = r[i]
        if step:
            x[i] = x[i] + alpha * p[i]
            ri = ri - alpha * q[i]
            r[i] = ri
        zi = ri
        if precondition != 0:
            zi = inverse[i] * ri
        z[i] = zi
        rz += wp.dot(ri, zi)
        rr += wp.dot(ri, ri)
    rz_total = wp.tile_sum(wp.tile(rz))
    rr_total = wp.tile_sum(wp.tile(rr))
    if lane == 0:
        wp.atomic_add(state, RZ_NEW, rz_total[0])
        wp.atomic_add(state, RR, rr_total[0])


@wp.kernel(enable_backward=False)
def _step_p(state: wp.array(dtype=wp.float64), z: wp.array(dtype=wp.vec3d), p: wp.array(dtype=wp.vec3d),
            basis: wp.array(dtype=mat36d), aggregate: wp.array(dtype=int), values: wp.array(dtype=wp.float64),
            restricted: wp.array(dtype=wp.float64), first: int):
    """p = z + (r . z)_new / (r . z) p, or p = z before the first iteration (``first``); with a coarse level (``values``
    = A_c^-1 P^T r not empty) z is block-Jacobi's part and P values is added here, and P^T r (``restricted``, read)
    is cleared for the next iteration."""
    i = wp.tid()
    zi = z[i]
    if values.shape[0] > 0:
        zi = zi + prolong(basis, aggregate, values, i)
        for k in range(i, restricted.shape[0], p.shape[0]):  # one entry per thread where there are more nodes
            restricted[k] = wp.float64(0.0)
    if first != 0:
        p[i] = zi
    elif state[ACTIVE] != wp.float64(0.0) and state[PQ] > wp.float64(0.0) and state[RZ_NEW] > wp.float64(0.0):
        p[i] = zi + (state[RZ_NEW] / state[RZ]) * p[i]


@wp.kernel(enable_backward=False)
def _set_limits(limits: wp.array(dtype=wp.float64), rtol2: wp.float64, atol2: wp.float64, maxiter: wp.float64):
    """A solve's rtol^2, atol^2 and iteration cap, written outside its graph (the graph reads them from here)."""
    limits[0] = rtol2
    limits[1] = atol2
    limits[2] = maxiter


@wp.kernel(enable_backward=False)
def _start(state: wp.array(dtype=wp.float64), limits: wp.array(dtype=wp.float64), condition: wp.array(dtype=wp.int32)):
    """After the set-up's sums (|r|^2 -> RR, r . z -> RZ_NEW, |b|^2 -> TOL2): the tolerance max(rtol^2 |b|^2, atol^2),
    the stop where r is within it already (converged) or r . M r <= 0 (M not positive definite), otherwise the state of
    the first iteration."""
    tol2 = wp.max(limits[0] * state[TOL2], limits[1])
    rz = state[RZ_NEW]
    rr = state[RR]
    for k in range(STATE_SIZE):
        state[k] = wp.float64(0.0)
    state[TOL2] = tol2
    state[MAXITER] = limits[2]
    if rr <= tol2:
        state[STOP] = CONVERGED
    elif not rz > wp.float64(0.0):
        state[STOP] = PRECONDITIONER_NOT_DEFINITE
    else:
        state[RZ] = rz
        state[ACTIVE] = wp.float64(1.0)
    condition[0] = wp.where(state[ACTIVE] != wp.float64(0.0), 1, 0)


@wp.kernel(enable_backward=False)
def _decide(state: wp.array(dtype=wp.float64), condition: wp.array(dtype=wp.int32)):
    """After an iteration's updates: the stop reason, the iteration count and whether to go on; clears the sums
    for the next iteration."""
    if state[ACTIVE] != wp.float64(0.0):
        state[ITER] = state[ITER] + wp.float64(1.0)
        if not state[PQ] > wp.float64(0.0):
            state[STOP] = NOT_DEFINITE
        elif state[RR] <= state[TOL2]:
            state[STOP] = CONVERGED
        elif not state[RZ_NEW] > wp.float64(0.0):
            state[STOP] = PRECONDITIONER_NOT_DEFINITE
        elif state[ITER] >= state[MAXITER]:
            state[STOP] = ITERATION_CAP
        state[RZ] = state[RZ_NEW]
        if state[STOP] != wp.float64(0.0):
            state[ACTIVE] = wp.float64(0.0)
    state[RZ_NEW] = wp.float64(0.0)
    state[PQ] = wp.float64(0.0)
    state[RR] = wp.float64(0.0)
    condition[0] = wp.where(state[ACTIVE] != wp.float64(0.0), 1, 0)


def add_dot(a: wp.array, b: wp.array, out: wp.array, slot: int = 0) -> None:
    """out[slot] += a . b (vec3d arrays; out float64 on their device) without a host read: block-wise tile sums added
    atomically, as the CG's dot products."""
    wp.launch_tiled(_dot, dim=[DOT_BLOCKS], block_dim=DOT_THREADS, device=a.device,
                    inputs=[a, b, out, slot, DOT_BLOCKS])


class CgWorkspace:
    """``definite_cg``'s work vectors (b, r, z, p, q), state, limits and last captured CUDA graph, kept between
    solves of ``n`` 3-vectors on ``device`` (a solver's matrices change arrays only when their sparsity does)."""

    def __init__(self, n: int, device):
        self.b, self.r, self.z, self.p, self.q = (wp.empty(n, dtype=wp.vec3d, device=device) for _ in range(5))
        self.state = wp.zeros(STATE_SIZE, dtype=wp.float64, device=device)
        self.limits = wp.zeros(3, dtype=wp.float64, device=device)  # rtol^2, atol^2, iteration cap (``_set_limits``)
        self.x_max_work = reduction_buffer(2, device)  # max |x| and its NaN count at the end of a solve
        self.condition = wp.zeros(1, dtype=wp.int32, device=device)
        self.no_preconditioner = wp.empty(0, dtype=wp.mat33d, device=device)
        self.no_basis = wp.empty(0, dtype=mat36d, device=device)
        self.no_aggregate = wp.empty(0, dtype=int, device=device)
        self.no_values = wp.empty(0, dtype=wp.float64, device=device)
        self.graph_key: tuple | None = None  # (operator's graph_key, preconditioner, x) of ``graph``
        self.graph = None
        self.captures = 0  # graphs captured (the rest of the solves on CUDA launched a kept one)


def definite_cg(A: LinearOperator, b: wp.array, x: wp.array, rtol: float, maxiter: int,
                M: BlockJacobi | None = None, atol: float = 0.0, workspace: CgWorkspace | None = None,
                coarse: CoarseSpace | None = None) -> CgResult:
    """Solves A x = b from the given x (vec3d arrays, updated in place) to |b - A x| <= max(rtol |b|, atol),
    stopping early where A (or M) is found not to be positive definite (x then holds the last iterate).
    ``coarse`` (with M; its inverse made, ``CoarseSpace.ready``): M becomes the two-level preconditioner
    M + P A_c^-1 P^T (coarse_space.py).
    ``workspace``: work arrays and the graph kept from earlier solves of the same size (a new one otherwise); the graph is
    reused where A has a ``graph_key`` (sparse_product.py) and the preconditioner and x are the same (b is copied into
    the workspace, so it may differ)."""
    device = b.device
    if workspace is not None and not len(workspace.r) == len(b) == len(x):
        raise ValueError(f"CG workspace of {len(workspace.r)} 3-vectors for b of {len(b)} and x of {len(x)}")
    ws = workspace if workspace is not None else CgWorkspace(len(b), device)
    r, z, p, q, state, condition = ws.r, ws.z, ws.p, ws.q, ws.state, ws.condition
    inverse = M.inverse_blocks if M is not None else ws.no_preconditioner
    if coarse is not None and not (M is not None and coarse.ready):
        raise ValueError("a coarse level needs the block-Jacobi preconditioner and a coarse inverse")
    prolonged = (coarse.basis, coarse.aggregate, coarse.values, coarse.restricted) if coarse is not None else \
        (ws.no_basis, ws.no_aggregate, ws.no_values, ws.no_values)

    def tiled(kernel, *inputs):
        wp.launch_tiled(kernel, dim=[DOT_BLOCKS], block_dim=DOT_THREADS, device=device,
                        inputs=[*inputs, DOT_BLOCKS])

    def step_precondition():
        tiled(_step_precondition, state, p, q, inverse, int(M is not None), x, r, z)
        if coarse is not None:
            coarse.solve(r, state, RZ_NEW)

    def start():  # r = b - A x, z = M r, p = z, their sums (ACTIVE 0: no step), then the state of the first iteration
        state.zero_()
        if coarse is not None:
            coarse.restricted.zero_()
        A.matvec(x, ws.b, r, -1.0, 1.0)
        step_precondition()
        wp.launch(_step_p, dim=len(p), device=device, inputs=[state, z, p, *prolonged, 1])
        tiled(_dot, ws.b, ws.b, state, TOL2)
        wp.launch(_start, dim=1, device=device, inputs=[state, ws.limits, condition])

    def iteration():
        A.matvec(p, q, q, 1.0, 0.0)
        tiled(_dot, p, q, state, PQ)
        step_precondition()
        wp.launch(_step_p, dim=len(p), device=device, inputs=[state, z, p, *prolonged, 0])
        wp.launch(_decide, dim=1, device=device, inputs=[state, condition])

    def unrolled():
        for _ in range(UNROLL):
            iteration()

    def finish():  # max |x|, its NaN count and x . b into the state, read with it
        launch_max_abs(x, ws.x_max_work)
        wp.copy(state, ws.x_max_work, dest_offset=X_MAX, count=2)
        add_dot(x, ws.b, state, XB)

    wp.copy(ws.b, b)
    wp.launch(_set_limits, dim=1, device=device, inputs=[ws.limits, rtol * rtol, atol * atol, float(maxiter)])
    if not device.is_cuda:
        start()
        wp.capture_while(condition, iteration)  # on the CPU: a host loop on the condition
        finish()
    else:  # with conditional graphs (CUDA 12.4+) the whole solve is the graph, otherwise one iteration
        conditional = wp.is_conditional_graph_supported()
        key = getattr(A, "graph_key", None)
        key = key and (key, inverse.ptr, x.ptr, coarse is not None and coarse.inverse.ptr)
        graph = ws.graph if key and key == ws.graph_key else None
        if not conditional:
            start()
        if graph is None:
            if conditional:  # outside any capture, to load the kernels' modules (the captured solve starts again)
                start()
                finish()
            else:
                iteration()
            with wp.ScopedCapture(device=device, force_module_load=False) as capture:
                if conditional:
                    start()
                    wp.capture_while(condition, unrolled)
                    finish()
                else:
                    iteration()
            graph = capture.graph
            ws.captures += 1
            if key:
                ws.graph_key, ws.graph = key, graph
        if conditional:
            wp.capture_launch(graph)
        else:  # launched CHECK_EVERY times between reads of the condition
            while int(condition.numpy()[0]):
                for _ in range(CHECK_EVERY):
                    wp.capture_launch(graph)
            finish()
    s = state.numpy()
    converged, not_definite, not_definite_m, _ = _STOPS
    return CgResult(bool(s[STOP] == converged), bool(s[STOP] in (not_definite, not_definite_m)), int(s[ITER]),
                    float("nan") if s[X_NANS] else float(s[X_MAX]), float(s[XB]))
