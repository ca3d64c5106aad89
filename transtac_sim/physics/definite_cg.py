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
start (r, z, p, |b|^2, then the tolerance and the stop tests before the first iteration, ``start_state``), the loop
(``wp.capture_while``) and max |x| at the end (reductions.py, copied into the state). The host writes only the solve's
tolerances, cap and start into pinned memory, which the graph copies in at its start, and reads the state once, at the
end (one launch of the graph per solve, and a copy of b where it is not the workspace's own, unless the caller has the
graph take b and set x = 0 itself: ``fixed``, device_linear.py's solves); without conditional graphs one pass of the
loop is captured and launched ``CHECK_EVERY`` times between host reads. An iteration is four launches, five with the
coarse level: the product, p . q, then one kernel for the updates of x and r, z = M r, r . z, |r|^2 and, with the coarse
level, P^T r (cg_kernels.py ``_step_precondition``: one thread group per aggregate, over its nodes), the coarse product
A_c^-1 P^T r (which adds its part of r . z), and the update of p (which adds the coarse part of z) with the stop test
done by its first thread (``_step_p``, cg_kernels.py too). The stop test and the p update share a launch because the
iteration's sums live in one of three sets of state slots, taken in turn (iteration k uses set k mod 3, and reads the
previous r . z from set k - 1): the test writes the next set's flag and clears its sums while the other threads still
read this set's and the previous one's. With P^T r formed in the update of r, over the arms of coarse_space.py, a solve
of press_slide's Newton system (H100) took 0.87-0.91x the time at the same CG iterations (a whole iteration 46.1 instead
of 48.9 us in scripts/bench_cg_kernels.py), and the device CG's phase 0.88-0.93x per call in its frames (BENCHMARKS.md
``fem_cg_fused_gpu``). The state (the three sets of the flag that the solve goes on, p . q, r . z and |r|^2; the
tolerance, stop reason, iteration and iteration cap; at the end max |x|, its NaN count and x . b) is one small float64
array, so the iterations of a stopped solve change nothing (x, r and p keep their values). A pass of the captured loop
therefore runs ``UNROLL`` iterations (a multiple of 3, so that each pass starts at set 0), and a solve pays for at most
UNROLL - 1 iterations after its stop: on press_slide's Newton system (H100) 4 iterations a pass took 0.93-0.96x the time
of 1 (BENCHMARKS.md ``fem_cg_unrolled_gpu``, scripts/bench_cg_kernels.py), and 6 at most about 2 % less than 3 per solve
from 0, while a short solve (a step estimate) pays for up to 5 iterations after its stop instead of 2
(``fem_cg_fused_gpu``). Dot products are block-wise tile sums added atomically (round-off varies from run to run in the
last bits, as the assembly's atomics already do).

A ``CgWorkspace`` (cg_kernels.py, with the state's layout and the kernels) keeps the work vectors (b copied into its
own), the state and the last ``KEPT_GRAPHS`` captured graphs between solves of one size (a solver's Newton systems): a
solve whose arrays are those of an earlier one (the operator's ``graph_key``, the preconditioner, x and, with ``fixed``,
b) launches that solve's graph instead of capturing and instantiating its own (press_slide on an H100: one graph for all
its frames, 0.87x the CG's time per solve; BENCHMARKS.md ``fem_cg_kept_graphs_gpu``; a second one since b is taken
inside it, for the predicted contact's solves of a release frame, contact_prediction.py). The state is cleared at the
start of every solve. Before the start moved into the graph, a solve read the state twice, and the GPU waited between
the two reads while the host wrote the state of the first iteration and launched the loop (scripts/fem_host_census.py;
BENCHMARKS.md ``fem_host_census_gpu``).
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp
from warp.optim.linear import LinearOperator

from transtac_sim.physics.cg_kernels import (
    ITER,
    PQ,
    RZ,
    SET_SIZE,
    SETS,
    STOP,
    STOPS,
    TOL2,
    X_MAX,
    X_NANS,
    XB,
    CgWorkspace,
    add_dot,
    launch_p_update,
    launch_step_precondition,
    start_state,
    take_b,
)
from transtac_sim.physics.coarse_space import CoarseSpace
from transtac_sim.physics.reductions import launch_max_abs
from transtac_sim.physics.sparse_product import BlockJacobi

CHECK_EVERY = 3  # host path without conditional graphs: passes of the loop (UNROLL iterations each) between reads
UNROLL = 3  # iterations per pass of the loop (a multiple of SETS)
#: CUDA graphs a workspace keeps, one per solve's arrays (the least recently used dropped first): device_linear.py's
#: solves take b from Newton's right-hand side or a predicted contact's (contact_prediction.py), with the float32 or
#: float64 product
KEPT_GRAPHS = 4


@dataclass(frozen=True)
class CgResult:
    converged: bool
    not_definite: bool  # stopped at p . A p <= 0 (or r . M r <= 0): the matrix (or M) is not positive definite
    iterations: int
    x_max: float  # max |x| over its entries and components at the end (NaN where an entry is NaN)
    x_dot_b: float  # x . b at the end (Newton's slope along its step, with b = -g: newton.py)


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
            wp.launch(take_b, dim=len(b), device=device, inputs=[b, fixed, ws.b, x, ws.limits])
        A.matvec(x, ws.b, r, -1.0, 1.0)
        step_precondition(SETS - 1)
        launch_p_update(ws, SETS - 1, coarse, first=True)
        add_dot(ws.b, ws.b, state, TOL2)
        wp.launch(start_state, dim=1, device=device, inputs=[state, ws.limits, condition])

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
    converged, not_definite, not_definite_m, _ = STOPS
    return CgResult(bool(s[STOP] == converged), bool(s[STOP] in (not_definite, not_definite_m)), int(s[ITER]),
                    float("nan") if s[X_NANS] else float(s[X_MAX]), float(s[XB]))
