"""The device CG's state layout, work space and kernels (definite_cg.py, which says how they fit together): the state's
three sets of an iteration's slots and the solve's own slots, the dot product, the update of x, r and z with the sums
r . z and |r|^2 (and P^T r with a coarse level), the update of p with the stop test, and the solve's start.
"""

from __future__ import annotations

import warp as wp

from transtac_sim.physics.coarse_space import (
    AGGREGATE_THREADS,
    CoarseSpace,
    group_range,
    prolong,
    restrict_node,
    vec6d,
)
from transtac_sim.physics.reductions import free_part, reduction_buffer

DOT_BLOCKS = 256  # thread blocks of a dot product (each strides over the vector)
DOT_THREADS = 256

# the state array: SETS sets of an iteration's slots (iteration k uses set k mod SETS: whether it goes on, and its sums
# p . q, r . z and |r|^2), then the solve's (X_MAX, X_NANS: max |x| over entries and components at the end, and the
# entries with a NaN; XB: x . b at the end)
SETS = wp.constant(3)
ACTIVE, PQ, RZ, RR = (wp.constant(k) for k in range(4))
SET_SIZE = wp.constant(4)
TOL2, STOP, ITER, MAXITER, X_MAX, X_NANS, XB = (wp.constant(SETS * SET_SIZE + k) for k in range(7))
# the limits array: rtol^2, atol^2, the iteration cap (read by ``start_state``), then whether x = 0 first (``take_b``)
LIMITS = 4
FROM_ZERO = wp.constant(3)
STATE_SIZE = SETS * SET_SIZE + 7
vec8d = wp.types.vector(length=8, dtype=wp.float64)
# why it stopped (the STOP slot)
STOPS = (1.0, 2.0, 3.0, 4.0)
CONVERGED, NOT_DEFINITE, PRECONDITIONER_NOT_DEFINITE, ITERATION_CAP = (wp.constant(wp.float64(k)) for k in STOPS)


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
def take_b(b: wp.array(dtype=wp.vec3d), fixed: wp.array(dtype=wp.vec3d), into: wp.array(dtype=wp.vec3d),
            x: wp.array(dtype=wp.vec3d), limits: wp.array(dtype=wp.float64)):
    """The solve's own right-hand side ``into`` = (I - P) b, P the diagonal 0/1 mask of the ``fixed`` components, and
    x = 0 where the limits say so (``FROM_ZERO``, written by the host for each solve): a solve's first launch, inside
    its graph."""
    i = wp.tid()
    into[i] = free_part(b[i], fixed[i])
    if limits[FROM_ZERO] != wp.float64(0.0):
        x[i] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))


@wp.kernel(enable_backward=False)
def start_state(state: wp.array(dtype=wp.float64), limits: wp.array(dtype=wp.float64),
                condition: wp.array(dtype=wp.int32)):
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
