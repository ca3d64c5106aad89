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

M is block-Jacobi (sparse_product.py ``BlockJacobi``: the inverses of the 3x3 diagonal blocks), block-Jacobi plus a
coarse correction on rigid-body modes of aggregates of nodes (``coarse``: coarse_space.py), or none. It runs on the
device like ``warp.optim.linear.cg``, but with conditional CUDA graphs (CUDA 12.4+) the whole solve is one graph: the
start (r, z, p, |b|^2, then the tolerance and the stop tests before the first iteration, ``_start``), the loop
(``wp.capture_while``) and max |x| at the end (reductions.py, copied into the state). The host writes only the
solve's tolerances, cap and start into pinned memory, which the graph copies in at its start, and reads the state
once, at the end (one launch of the graph per solve, and a copy of b where it is not the workspace's own, unless the
caller has the graph take b and set x = 0 itself: ``fixed``, device_linear.py's solves); without conditional
graphs one pass of the loop is captured and launched ``CHECK_EVERY`` times between host reads. An iteration is four
launches, five with the coarse level: the product, p . q, then one kernel for the updates of x and r, z = M r, r . z,
|r|^2 and, with the coarse level, P^T r (``_step_precondition``: one thread group per aggregate, over its nodes), the
coarse product A_c^-1 P^T r (which adds its part of r . z), and the update of p (which adds the coarse part of z) with
the stop test done by its first thread (``_step_p``). The stop test and the p update share a launch because the
iteration's sums live in one of three sets of state slots, taken in turn (iteration k uses set k mod 3, and reads the
previous r . z from set k - 1): the test writes the next set's flag and clears its sums while the other threads still
read this set's and the previous one's. With P^T r formed in the update of r, over the arms of coarse_space.py, a
solve of press_slide's Newton system (H100) took 0.87-0.91x the time at the same CG iterations (a whole iteration
46.1 instead of 48.9 us in scripts/bench_cg_kernels.py), and the device CG's phase 0.88-0.93x per call in its frames
(BENCHMARKS.md ``fem_cg_fused_gpu``). The
state (the three sets of the flag that the solve goes on, p . q, r . z and |r|^2; the tolerance, stop reason, iteration
and iteration cap; at the end max |x|, its NaN count and x . b) is one small float64 array, so the iterations of a
stopped solve change nothing (x, r and p keep their values). A pass of the captured loop therefore runs ``UNROLL``
iterations (a multiple of 3, so that each pass starts at set 0), and a solve pays for at most UNROLL - 1 iterations
after its stop: on press_slide's Newton system (H100) 4 iterations a pass took 0.93-0.96x the time of 1
(BENCHMARKS.md ``fem_cg_unrolled_gpu``, scripts/bench_cg_kernels.py), and 6 at most about 2 % less than 3 per
solve from 0, while a short solve (a step estimate) pays for up to 5 iterations after its stop instead of 2
(``fem_cg_fused_gpu``). Dot products are block-wise tile sums added atomically (round-off varies from run to run in
the last bits, as the assembly's atomics already do).

A ``CgWorkspace`` keeps the work vectors (b copied into its own), the state and the last ``KEPT_GRAPHS`` captured
graphs between solves of one size (a solver's Newton systems): a solve whose arrays are those of an earlier one (the
operator's ``graph_key``, the preconditioner, x and, with ``fixed``, b) launches that solve's graph instead of capturing
and instantiating its own (press_slide on an H100: one graph for all its frames, 0.87x the CG's time per solve;
BENCHMARKS.md ``fem_cg_kept_graphs_gpu``; a second one since b is taken inside it, for the predicted contact's solves
of a release frame, contact_prediction.py). The state
is cleared at the start of every solve. Before the start moved into the graph, a solve read the state twice, and the
GPU waited between the two reads while the host wrote the state of the first iteration and launched the loop
(scripts/fem_host_census.py; BENCHMARKS.md ``fem_host_census_gpu``).
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp
from warp.optim.linear import LinearOperator

from transtac_sim.physics.coarse_space import (
    AGGREGATE_THREADS,
    CoarseSpace,
    group_range,
    prolong,
    restrict_node,
    vec6d,
)
from transtac_sim.physics.reductions import free_part, launch_max_abs, reduction_buffer
from transtac_sim.physics.sparse_product import BlockJacobi

CHECK_EVERY = 3  # host path without conditional graphs: passes of the loop (UNROLL iterations each) between reads
UNROLL = 3  # iterations per pass of the loop (a multiple of SETS)
DOT_BLOCKS = 256  # thread blocks of a dot product (each strides over the vector)
DOT_THREADS = 256
#: CUDA graphs a workspace keeps, one per solve's arrays (the least recently used dropped first): device_linear.py's
#: solves take b from Newton's right-hand side or a predicted contact's (contact_prediction.py), with the float32 or
#: float64 product
KEPT_GRAPHS = 4

# the state array: SETS sets of an iteration's slots (iteration k uses set k mod SETS: whether it goes on, and its sums
# p . q, r . z and |r|^2), then the solve's (X_MAX, X_NANS: max |x| over entries and components at the end, and the
# entries with a NaN; XB: x . b at the end)
SETS = wp.constant(3)
ACTIVE, PQ, RZ, RR = (wp.constant(k) for k in range(4))
SET_SIZE = wp.constant(4)
TOL2, STOP, ITER, MAXITER, X_MAX, X_NANS, XB = (wp.constant(SETS * SET_SIZE + k) for k in range(7))
# the limits array: rtol^2, atol^2, the iteration cap (read by ``_start``), then whether x = 0 first (``_take_b``)
LIMITS = 4
FROM_ZERO = wp.constant(3)
STATE_SIZE = SETS * SET_SIZE + 7
vec8d = wp.types.vector(length=8, dtype=wp.float64)
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
def _dot(a: wp.array(dtype=wp.vec3d), b: wp.array(dtype=wp.vec3d), state: wp.array(dtype=wp.float64), slot: int,
         blocks: int):
    block, lane = wp.tid()
    partial = wp.float64(0.0)
    for i in range(block * wp.block_dim() + lane, a.shape[0], blocks * wp.block_dim()):
        partial += wp.dot(a[i], b[i])
    total = wp.tile_sum(wp.tile(partial))
    if lane == 0:
        wp.atomic_add(state, slot, total[0])


@wp.func
def _previous(set_: int):
    """The first slot of the set before ``set_`` (the previous iteration's: its r . z is this one's previous r . z)."""
    return SET_SIZE * ((set_ + SETS - 1) % SETS)


@wp.kernel(enable_backward=False)
def _step_precondition(state: wp.array(dtype=wp.float64), set_: int, p: wp.array(dtype=wp.vec3d),
                       q: wp.array(dtype=wp.vec3d), inverse: wp.array(dtype=wp.mat33d), precondition: int,
                       x: wp.array(dtype=wp.vec3d), r: wp.array(dtype=wp.vec3d), z: wp.array(dtype=wp.vec3d),
                       members: wp.array(dtype=int), starts: wp.array(dtype=int), arm: wp.array(dtype=wp.vec3d),
                       free: wp.array(dtype=wp.vec3d), restricted: wp.array(dtype=wp.float64)):
    """x += alpha p, r -= alpha q (alpha = r.z (previous set) / p.q), z = M r (block-Jacobi), and the sums r . z and
    |r|^2 into set ``set_``; one thread group per aggregate of the coarse level (``members``, ``starts``), which also
    writes its part of P^T r into ``restricted``, or per ``AGGREGATE_THREADS`` nodes without it (``members``,
    ``starts``, ``arm``, ``free`` and ``restricted`` empty). The
    coarse level's part of z is added where p is updated (``_step_p``) and its part of r . z by the coarse product."""
    group, lane = wp.tid()
    now = SET_SIZE * set_
    step = state[now + ACTIVE] != wp.float64(0.0) and state[now + PQ] > wp.float64(0.0)
    alpha = wp.float64(0.0)
    if step:
        alpha = state[_previous(set_) + RZ] / state[now + PQ]
    nodes = group_range(starts, group, x.shape[0])
    sums = vec8d()  # r . z, |r|^2, P^T r
    for k in range(nodes[0] + lane, nodes[1], wp.block_dim()):
        i = k
        if members.shape[0] > 0:
            i = members[k]
        ri = r[i]
        if step:
            x[i] = x[i] + alpha * p[i]
            ri = ri - alpha * q[i]
            r[i] = ri
        zi = ri
        if precondition != 0:
            zi = inverse[i] * ri
        z[i] = zi
        v = vec6d()
        if restricted.shape[0] > 0:
            v = restrict_node(arm[i], free[i], ri)
        sums += vec8d(wp.dot(ri, zi), wp.dot(ri, ri), v[0], v[1], v[2], v[3], v[4], v[5])
    total = wp.tile_sum(wp.tile(sums, preserve_type=True))[0]
    if lane == 0:
        wp.atomic_add(state, now + RZ, total[0])
        wp.atomic_add(state, now + RR, total[1])
        if restricted.shape[0] > 0:
            for c in range(6):
                restricted[6 * group + c] = total[2 + c]


@wp.func
def _decide(state: wp.array(dtype=wp.float64), now: int, following: int, condition: wp.array(dtype=wp.int32)):
    """After an iteration's updates (its sums in set ``now``): the stop reason, the iteration count and whether to go on
    (the ``following`` set's flag, whose sums are cleared for the next iteration)."""
    going = wp.float64(0.0)
    if state[now + ACTIVE] != wp.float64(0.0):
        state[ITER] = state[ITER] + wp.float64(1.0)
        if not state[now + PQ] > wp.float64(0.0):
            state[STOP] = NOT_DEFINITE
        elif state[now + RR] <= state[TOL2]:
            state[STOP] = CONVERGED
        elif not state[now + RZ] > wp.float64(0.0):
            state[STOP] = PRECONDITIONER_NOT_DEFINITE
        elif state[ITER] >= state[MAXITER]:
            state[STOP] = ITERATION_CAP
        if state[STOP] == wp.float64(0.0):
            going = wp.float64(1.0)
    state[following + ACTIVE] = going
    state[following + PQ] = wp.float64(0.0)
    state[following + RZ] = wp.float64(0.0)
    state[following + RR] = wp.float64(0.0)
    condition[0] = wp.where(going != wp.float64(0.0), 1, 0)


@wp.kernel(enable_backward=False)
def _step_p(state: wp.array(dtype=wp.float64), set_: int, z: wp.array(dtype=wp.vec3d), p: wp.array(dtype=wp.vec3d),
            arm: wp.array(dtype=wp.vec3d), free: wp.array(dtype=wp.vec3d), aggregate: wp.array(dtype=int),
            values: wp.array(dtype=wp.float64), condition: wp.array(dtype=wp.int32), first: int):
    """p = z + (r . z) / (r . z)_previous p, or p = z before the first iteration (``first``); with a coarse level
    (``values`` = A_c^-1 P^T r not empty) z is block-Jacobi's part and P values is added here. Thread 0 then runs the
    stop test (``_decide``; not before the first iteration): it writes only the next set, which no thread reads here."""
    i = wp.tid()
    zi = z[i]
    if values.shape[0] > 0:
        zi = zi + prolong(arm, free, aggregate, values, i)
    if first != 0:
        p[i] = zi
        return
    now = SET_SIZE * set_
    rz = state[now + RZ]
    if state[now + ACTIVE] != wp.float64(0.0) and state[now + PQ] > wp.float64(0.0) and rz > wp.float64(0.0):
        p[i] = zi + (rz / state[_previous(set_) + RZ]) * p[i]
    if i == 0:
        _decide(state, now, SET_SIZE * ((set_ + 1) % SETS), condition)


@wp.kernel(enable_backward=False)
def _take_b(b: wp.array(dtype=wp.vec3d), fixed: wp.array(dtype=wp.vec3d), into: wp.array(dtype=wp.vec3d),
            x: wp.array(dtype=wp.vec3d), limits: wp.array(dtype=wp.float64)):
    """The solve's own right-hand side ``into`` = (I - P) b, P the diagonal 0/1 mask of the ``fixed`` components, and
    x = 0 where the limits say so (``FROM_ZERO``, written by the host for each solve): a solve's first launch, inside
    its graph."""
    i = wp.tid()
    into[i] = free_part(b[i], fixed[i])
    if limits[FROM_ZERO] != wp.float64(0.0):
        x[i] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.kernel(enable_backward=False)
def _start(state: wp.array(dtype=wp.float64), limits: wp.array(dtype=wp.float64), condition: wp.array(dtype=wp.int32)):
    """After the set-up's sums (|r|^2 and r . z into the last set, |b|^2 -> TOL2): the tolerance max(rtol^2 |b|^2,
    atol^2), the stop where r is within it already (converged) or r . M r <= 0 (M not positive definite), otherwise the
    state of the first iteration (set 0 going on, r . z kept in the last set as its previous one)."""
    tol2 = wp.max(limits[0] * state[TOL2], limits[1])
    last = (SETS - 1) * SET_SIZE
    rz = state[last + RZ]
    rr = state[last + RR]
    for k in range(STATE_SIZE):
        state[k] = wp.float64(0.0)
    state[TOL2] = tol2
    state[MAXITER] = limits[2]
    if rr <= tol2:
        state[STOP] = CONVERGED
    elif not rz > wp.float64(0.0):
        state[STOP] = PRECONDITIONER_NOT_DEFINITE
    else:
        state[last + RZ] = rz
        state[ACTIVE] = wp.float64(1.0)
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
        self.limits = wp.zeros(LIMITS, dtype=wp.float64, device=device)  # rtol^2, atol^2, iteration cap, x = 0 first
        # the limits as the host writes them (pinned on a GPU, so that the solve's graph copies them in at each replay)
        self.limits_host = wp.zeros(LIMITS, dtype=wp.float64, device="cpu", pinned=wp.get_device(device).is_cuda)
        self.x_max_work = reduction_buffer(2, device)  # max |x| and its NaN count at the end of a solve
        self.condition = wp.zeros(1, dtype=wp.int32, device=device)
        self.no_preconditioner = wp.empty(0, dtype=wp.mat33d, device=device)
        self.no_nodes = wp.empty(0, dtype=int, device=device)
        self.no_arms = wp.empty(0, dtype=wp.vec3d, device=device)
        self.no_values = wp.empty(0, dtype=wp.float64, device=device)
        # (the arrays a graph reads, the graph) by key: the operator's ``graph_key``, the preconditioner, x, the coarse
        # inverse and, where the solve takes b itself (``definite_cg``'s ``fixed``), b and the mask
        self.graphs: dict[tuple, tuple[tuple, object]] = {}
        self.captures = 0  # graphs captured (the rest of the solves on CUDA launched a kept one)


def launch_step_precondition(ws: CgWorkspace, set_: int, x: wp.array, inverse: wp.array,
                             coarse: CoarseSpace | None) -> None:
    """``_step_precondition`` on the workspace's vectors and x, its sums into set ``set_``: one thread group per
    aggregate of ``coarse`` (which also sums P^T r into its ``restricted``), or per ``AGGREGATE_THREADS`` nodes without
    it; ``inverse``: block-Jacobi's inverse blocks (empty: no preconditioner)."""
    if coarse is not None:
        groups, nodes = coarse.aggregates, (coarse.members, coarse.starts, coarse.arm, coarse.free, coarse.restricted)
    else:
        groups = (len(x) + AGGREGATE_THREADS - 1) // AGGREGATE_THREADS
        nodes = (ws.no_nodes, ws.no_nodes, ws.no_arms, ws.no_arms, ws.no_values)
    wp.launch_tiled(_step_precondition, dim=[groups], block_dim=AGGREGATE_THREADS, device=x.device,
                    inputs=[ws.state, set_, ws.p, ws.q, inverse, int(inverse.shape[0] > 0), x, ws.r, ws.z, *nodes])


def launch_p_update(ws: CgWorkspace, set_: int, coarse: CoarseSpace | None, first: bool) -> None:
    """``_step_p`` on the workspace's vectors for set ``set_`` (the stop test included but where ``first``), adding the
    coarse part of z where ``coarse`` is given."""
    prolonged = (coarse.arm, coarse.free, coarse.aggregate, coarse.values) if coarse is not None else \
        (ws.no_arms, ws.no_arms, ws.no_nodes, ws.no_values)
    wp.launch(_step_p, dim=len(ws.p), device=ws.p.device,
              inputs=[ws.state, set_, ws.z, ws.p, *prolonged, ws.condition, int(first)])


def definite_cg(A: LinearOperator, b: wp.array, x: wp.array, rtol: float, maxiter: int,
                M: BlockJacobi | None = None, atol: float = 0.0, workspace: CgWorkspace | None = None,
                coarse: CoarseSpace | None = None, fixed: wp.array | None = None, from_zero: bool = False) -> CgResult:
    """Solves A x = b from the given x (vec3d arrays, updated in place) to |b - A x| <= max(rtol |b|, atol),
    stopping early where A (or M) is found not to be positive definite (x then holds the last iterate).
    ``coarse`` (with M; its inverse made, ``CoarseSpace.ready``): M becomes the two-level preconditioner
    M + P A_c^-1 P^T (coarse_space.py).
    ``from_zero``: x = 0 first (instead of the given x).
    ``workspace``: work arrays and the graphs kept from earlier solves of the same size (a new one otherwise); a graph
    is reused where A has a ``graph_key`` (sparse_product.py) and the preconditioner and x are the same. b is copied
    into the workspace before the solve, so it may differ (where b is the workspace's own ``b``, nothing is copied), and
    x set to 0 there; with ``fixed`` (the 0/1 mask of the fixed components, vec3d per node) the solve's first launch
    takes (I - P) b and sets x = 0 itself (two launches fewer before it), and its graph is then kept per b too (a kept
    array of the caller's; the workspace holds it)."""
    device = b.device
    if workspace is not None and not len(workspace.r) == len(b) == len(x):
        raise ValueError(f"CG workspace of {len(workspace.r)} 3-vectors for b of {len(b)} and x of {len(x)}")
    ws = workspace if workspace is not None else CgWorkspace(len(b), device)
    r, p, q, state, condition = ws.r, ws.p, ws.q, ws.state, ws.condition
    inverse = M.inverse_blocks if M is not None else ws.no_preconditioner
    if coarse is not None and not (M is not None and coarse.ready):
        raise ValueError("a coarse level needs the block-Jacobi preconditioner and a coarse inverse")
    if UNROLL % SETS:
        raise ValueError(f"definite_cg.UNROLL must be a multiple of {SETS} (the state's sets), got {UNROLL}")

    def step_precondition(set_: int):
        launch_step_precondition(ws, set_, x, inverse, coarse)
        if coarse is not None:
            coarse.apply_inverse(state, SET_SIZE * set_ + RZ)

    def start():  # the limits in, b and x where the solve takes them, r = b - A x, z = M r, p = z, their sums in the
        # last set (not going on: no step), then the state of the first iteration
        wp.copy(ws.limits, ws.limits_host)  # the host's tolerances and cap (pinned on a GPU: read at each replay)
        state.zero_()
        if fixed is not None:
            wp.launch(_take_b, dim=len(b), device=device, inputs=[b, fixed, ws.b, x, ws.limits])
        A.matvec(x, ws.b, r, -1.0, 1.0)
        step_precondition(SETS - 1)
        launch_p_update(ws, SETS - 1, coarse, first=True)
        add_dot(ws.b, ws.b, state, TOL2)
        wp.launch(_start, dim=1, device=device, inputs=[state, ws.limits, condition])

    def unrolled():  # iterations 0 .. UNROLL - 1 of a pass, with the sets 0, 1, 2, 0, ...
        for k in range(UNROLL):
            A.matvec(p, q, q, 1.0, 0.0)
            add_dot(p, q, state, SET_SIZE * (k % SETS) + PQ)
            step_precondition(k % SETS)
            launch_p_update(ws, k % SETS, coarse, first=False)

    def finish():  # max |x|, its NaN count and x . b into the state, read with it
        launch_max_abs(x, ws.x_max_work)
        wp.copy(state, ws.x_max_work, dest_offset=X_MAX, count=2)
        add_dot(x, ws.b, state, XB)

    if fixed is not None and not len(fixed) == len(b):
        raise ValueError(f"a fixed mask of {len(fixed)} nodes for b of {len(b)}")
    if fixed is None:
        if b.ptr != ws.b.ptr:  # the caller may have written b into the workspace itself
            wp.copy(ws.b, b)
        if from_zero:
            x.zero_()
    # written in place: no earlier solve still reads them (each ends in a read of its state)
    ws.limits_host.numpy()[:] = (rtol * rtol, atol * atol, float(maxiter), float(from_zero))
    if not device.is_cuda:
        start()
        wp.capture_while(condition, unrolled)  # on the CPU: a host loop on the condition
        finish()
    else:  # with conditional graphs (CUDA 12.4+) the whole solve is the graph, otherwise one pass of the loop
        conditional = wp.is_conditional_graph_supported()
        key = getattr(A, "graph_key", None)
        taken = (b.ptr, fixed.ptr) if fixed is not None else ()
        key = key and (key, inverse.ptr, x.ptr, coarse is not None and coarse.inverse.ptr, *taken)
        kept = ws.graphs.pop(key, None) if key else None
        if kept is not None:  # moved to the end: the least recently used is dropped first
            ws.graphs[key] = kept
        graph = kept[1] if kept is not None else None
        if not conditional:
            start()
        if graph is None:
            if conditional:  # outside any capture, to load the kernels' modules (the captured solve starts again)
                start()
                finish()
            else:  # the first pass, run as it loads the modules (the captured passes follow it)
                unrolled()
            with wp.ScopedCapture(device=device, force_module_load=False) as capture:
                if conditional:
                    start()
                    wp.capture_while(condition, unrolled)
                    finish()
                else:
                    unrolled()
            graph = capture.graph
            ws.captures += 1
            if key:
                if len(ws.graphs) >= KEPT_GRAPHS:
                    del ws.graphs[next(iter(ws.graphs))]
                ws.graphs[key] = ((b, fixed, x), graph)
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
