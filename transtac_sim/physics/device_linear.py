"""The device path of the Newton steps' linear solves (linear.py ``LinearSolver`` with ``method="cg"``):
conjugate gradients on the solver's device (the GPU path), preconditioned with block-Jacobi plus a coarse
correction on rigid-body modes of aggregates of nodes (coarse_space.py; its inverse made from the first converged
system and again every ``COARSE_REFRESH_STEPS`` load steps; press_slide on an H100: 0.43x the CG iterations, 0.69x
the CG's time, BENCHMARKS.md ``fem_coarse_level_gpu``), stopping
where the matrix is found not to be positive definite (definite_cg.py; ``solve(..., definite=True)`` then
returns None), its matrix-vector product one warp per block row on the matrix rounded to float32 (sparse_product.py:
half the bytes of the product that is most of CG's time); the fixed rows/columns are
projected out in place (``_project_fixed_blocks``, on the blocks it changes). Its relative tolerance is Newton's
forcing term (inexact Newton: loose far from the solution, tight near it, but no tighter than the force test needs
where a scene has it: ``LinearSolver.solve``'s ``tight``, convergence_tests.py ``_force_forcing``). The tight tolerance
``cg_tol`` (of both paths) is a relative residual of 1e-4, not 1e-8: near convergence it only has to tell whether the
Newton step is below newton_tol_mm, and on
press_slide (H100, BENCHMARKS.md ``fem_cg_tolerance_gpu``) 1e-4 moved the markers by at most 2.1e-7 mm and the
forces by nothing in the printed digits, with 39 % fewer CG iterations and 1.3x faster frames. The price: at 1e-4
a CG step can be 10-50 % shorter than the exact one (scripts/bench_linear_solvers.py, ``linear_solvers_gpu``), so
a converged step may be up to about twice newton_tol_mm (2e-5 mm by default). Where the float32 product finds the
last Hessian Newton tries (``definite=False``) not positive definite, the system is solved again with the float64
product (``float64_solves`` counts them). The Gauss-Newton Hessian is positive definite in exact arithmetic, but near
inverted elements the inversion barrier's blocks dwarf the rest, and their rounding can make it look indefinite (the
likely cause): on train_random's sequence 72 (a cylinder pressed 1.47 mm, an H100) the shifted steps that followed
failed frames or ended one with a residual of 33 N, and with the float64 retry every frame converged without a shift
(BENCHMARKS.md ``fem_float64_fallback_gpu``). Where that is not solved either (CG stops at non-positive curvature or
at ``cg_maxiter``), the system is shifted in place, H + lambda |diag(H)| (Levenberg-Marquardt, ``SHIFTS``: towards a
scaled gradient step, always a descent direction), and solved again on the device; ``shifted_solves`` counts them
and ``last_shift`` tells Newton that the step is not a Newton step. The device path never hands a system to the host:
a host factorisation of a 10^5-dof P2 system takes seconds with CHOLMOD and, where CHOLMOD is missing (the GPU bundle),
SuperLU did not finish within minutes, which is what stalled train_random sequences 9 and 17 in ``generate`` on an H100
(BENCHMARKS.md ``fem_device_last_resort_gpu``). The last converged system's float32 matrix and
preconditioner are kept for ``solve_last`` (in ``DeviceWork``, with the CG's arrays and graph). Warp's FSAI halves
CG's iterations too, but its set-up (60 ms to 4 s on a 10^5-dof Newton system, H100) is made per system and costs
more than it saves (scripts/bench_linear_solvers.py, BENCHMARKS.md ``linear_solvers_gpu``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp
from warp.optim.linear import LinearOperator
from warp.sparse import BsrMatrix

from transtac_sim.physics.cg_kernels import CgWorkspace
from transtac_sim.physics.coarse_space import CoarseSpace
from transtac_sim.physics.definite_cg import CgResult, definite_cg
from transtac_sim.physics.replay import GraphCache
from transtac_sim.physics.sparse_product import (
    BlockJacobi,
    block_row_operator,
    diagonal_block,
    invert_diagonal,
    round_to_float32,
)


@wp.kernel(enable_backward=False)
def _project_fixed_blocks(touched: wp.array(dtype=int), rows: wp.array(dtype=int), columns: wp.array(dtype=int),
                          blocks: wp.array(dtype=wp.mat33d), fixed: wp.array(dtype=wp.vec3d)):
    """H <- (I - P) H (I - P) + P in place, P the diagonal 0/1 mask of the fixed components, on the blocks ``touched``
    (in block rows ``rows``): those whose row or column has a fixed component (``fixed_blocks``), the only ones the
    projection changes. What ``warp.fem.project_linear_system`` computes with two sparse matrix products and three
    copies."""
    t = wp.tid()
    k = touched[t]
    row = rows[t]
    col = columns[k]
    one = wp.vec3d(wp.float64(1.0), wp.float64(1.0), wp.float64(1.0))
    block = wp.diag(one - fixed[row]) * blocks[k] * wp.diag(one - fixed[col])
    if col == row:
        block += wp.diag(fixed[row])
    blocks[k] = block


def fixed_blocks(H: BsrMatrix, fixed: np.ndarray) -> tuple[wp.array, wp.array]:
    """(block indices, their block rows) of the blocks of H whose row or column node has a fixed component (``fixed``:
    bool, (nodes, 3)), on H's device: what ``_project_fixed_blocks`` changes (the bonded face's rows and columns; one
    thread per block row over every block took 309 us per call on press_slide on an H100, BENCHMARKS.md
    ``fem_slide_iterations_gpu``)."""
    offsets = H.offsets.numpy()
    counts = H.row_counts.numpy() if H.row_counts else np.diff(offsets)
    rows = np.repeat(np.arange(H.nrow), counts)
    k = np.repeat(offsets[:-1] - (np.cumsum(counts) - counts), counts) + np.arange(len(rows))  # skips unused slots
    node_fixed = fixed.any(axis=1)
    hit = node_fixed[rows] | node_fixed[H.columns.numpy()[k]]
    return (wp.array(k[hit].astype(np.int32), dtype=int, device=H.device),
            wp.array(rows[hit].astype(np.int32), dtype=int, device=H.device))


def project_fixed(H: BsrMatrix, fixed: wp.array, blocks: tuple[wp.array, wp.array]) -> None:
    """H <- (I - P) H (I - P) + P in place (``_project_fixed_blocks``), P = diag(``fixed``: 1.0 where fixed, vec3d per
    node), on the ``blocks`` of ``fixed_blocks``."""
    wp.launch(_project_fixed_blocks, dim=len(blocks[0]), device=H.device, inputs=[*blocks, H.columns, H.values, fixed])


@wp.kernel(enable_backward=False)
def _add_to_diagonal(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                     blocks: wp.array(dtype=wp.mat33d), d: wp.array(dtype=wp.vec3d), delta: wp.float64):
    """Each diagonal block B += delta diag(d[row]), in place (one thread per block row)."""
    row = wp.tid()
    k = diagonal_block(offsets, row_counts, columns, row)
    if k >= 0:
        blocks[k] = blocks[k] + delta * wp.diag(d[row])


@wp.kernel(enable_backward=False)
def _diagonal_magnitudes(offsets: wp.array(dtype=int), row_counts: wp.array(dtype=int), columns: wp.array(dtype=int),
                         blocks: wp.array(dtype=wp.mat33d), d: wp.array(dtype=wp.vec3d)):
    """d[row] = |diagonal| of the row's diagonal block (0 where it has none)."""
    row = wp.tid()
    k = diagonal_block(offsets, row_counts, columns, row)
    d[row] = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    if k >= 0:
        B = blocks[k]
        d[row] = wp.vec3d(wp.abs(B[0, 0]), wp.abs(B[1, 1]), wp.abs(B[2, 2]))


#: lambda of the device's last resort, H + lambda |diag(H)|, tried in turn; at 100 the block-Jacobi-preconditioned
#: system is close to the identity and CG converges in a few iterations
SHIFTS = (1.0e-2, 1.0, 1.0e2)


#: the device CG's coarse inverse (coarse_space.py) is made from the first converged system of the solver, then again
#: every this many load steps: making it (the Galerkin operator's atomic sums on the device, a Cholesky inverse of about
#: 1,000 unknowns on the host) costs about as much as a few CG solves, and one made a few frames earlier serves nearly as
#: well
COARSE_REFRESH_STEPS = 10

#: the step estimate (``solve_last``; newton.py) is solved to this relative residual, and on to ``cg_tol`` only where its
#: length is within the caller's [``refine_above``, ``exact_below``) (friction_lag.py ``_estimate_band``: about the
#: threshold Newton compares it with, where the comparison could go either way); the first stage in at most
#: ``ESTIMATE_CAP_FACTOR`` times the last converged system's CG iterations. Before, it was solved to 1e-3 within 1x those
#: iterations, which a system solved to Newton's loose forcing term did not reach: 58 of 103 estimates on the tiny
#: mesh with press_slide's motion (this CPU, the device path) ran to that cap and were thrown away, 45 % of the CG
#: iterations of the frames (BENCHMARKS.md ``fem_step_estimate``).
ESTIMATE_RTOL = 0.1
ESTIMATE_CAP_FACTOR = 2.0

#: the device path returns each solution in the next of this many kept arrays, taken in turn (no allocation per solve;
#: the rows of one array, so that a graph can read any of them: ``solution_row``): a solution stays valid until this
#: many more device solves have returned theirs (a solve that returns None takes none). Newton holds at most three at
#: once
#: (newton.py: a step estimate, the Newton step and a step solved with a predicted contact, contact_prediction.py)
SOLUTIONS = 4


@dataclass
class DeviceWork:
    """What the device path keeps between solves, so that each solve finds the arrays of the last and its CG can launch
    the graph captured then (definite_cg.py): the CG's workspace, x, the block-Jacobi inverses, the matrix's float32
    blocks (grown to the largest matrix), the coarse level of the two-level preconditioner (None: block-Jacobi
    alone), the graphs of the solves' set-up and the ``SOLUTIONS`` arrays the solutions are returned in (the rows of
    one array)."""

    cg: CgWorkspace
    x: wp.array
    inverse: wp.array
    rounded: wp.array
    coarse: CoarseSpace | None
    graphs: GraphCache  # the solves' set-up (``_solve_cg``)
    solutions: wp.array  # (SOLUTIONS, nodes): the solutions returned, a row each in turn (``_known_solution``)
    next_solution: int = 0


class DeviceSolves:
    """The device path's methods of ``LinearSolver`` (linear.py; which provides the fields they use: the fixed mask,
    tolerances, counters and the kept ``DeviceWork``)."""

    def _solve_shifted(self, H: BsrMatrix, rhs: wp.array, rtol: float) -> wp.array | None:
        """H + lambda |diag(H)| solved by the device CG for lambda in ``SHIFTS`` in turn (H, already projected, is
        changed in place), the first that converges; None if none does. Not kept for ``solve_last``: it is not the
        Hessian."""
        structure = [H.offsets, H.row_counts, H.columns, H.values]
        d = wp.empty(H.nrow, dtype=wp.vec3d, device=self.device)
        wp.launch(_diagonal_magnitudes, dim=H.nrow, device=self.device, inputs=[*structure, d])
        before = 0.0
        for lam in SHIFTS:
            wp.launch(_add_to_diagonal, dim=H.nrow, device=self.device,
                      inputs=[*structure, d, wp.float64(lam - before)])
            before = lam
            x = self._solve_cg(H, rhs, rtol, 0.0, coarse_from_this=False)
            if x is not None:
                self.shifted_solves += 1
                self.last_shift = lam
                self.forget()
                return x
        return None

    def _solve_last_cg(self, rhs: wp.array, exact_below: float, refine_above: float = 0.0) -> wp.array | None:
        """The step estimate on the device: the last converged system solved for ``rhs`` to ``ESTIMATE_RTOL`` in at most
        ``ESTIMATE_CAP_FACTOR`` times that system's CG iterations (at least 50), then on to ``cg_tol`` (within
        ``cg_maxiter``) where its max |x| is within [``refine_above``, ``exact_below``) mm; None where it does not
        converge."""
        if self._last_cg is None:
            return None
        A, M = self._last_cg
        x = self._device_work().x
        cap = max(50, int(ESTIMATE_CAP_FACTOR * self._converged_iterations))
        result, iterations = self._cg(A, M, rhs, x, ESTIMATE_RTOL, cap, exact_below, refine_above)
        self.estimate_iterations += iterations
        self.estimates_unconverged += not result.converged
        return self._known_solution(x, result) if result.converged else None  # a copy: the kept x is the next solve's

    def _device_work(self) -> DeviceWork:
        """The device path's arrays kept between solves (made on first use)."""
        if self._work is None:
            coarse = CoarseSpace(*self._coarse_setup, self.device) if self._coarse_setup is not None else None
            self._work = DeviceWork(CgWorkspace(self._node_count, self.device),
                                    wp.empty(self._node_count, dtype=wp.vec3d, device=self.device),
                                    wp.empty(self._node_count, dtype=wp.mat33d, device=self.device),
                                    wp.empty(0, dtype=wp.mat33f, device=self.device), coarse,
                                    GraphCache(self.device),
                                    wp.empty((SOLUTIONS, self._node_count), dtype=wp.vec3d, device=self.device))
        return self._work

    def coarse_stats(self) -> dict[str, int]:
        """The coarse level's size and how often its inverse was made or refused (empty without one)."""
        coarse = self._work.coarse if self._work is not None else None
        if coarse is None:
            return {}
        return {"coarse_unknowns": coarse.size, "coarse_updates": coarse.updates, "coarse_rejected": coarse.rejected,
                **{f"coarse_{k}_s": round(v, 3) for k, v in coarse.seconds.items()}}

    def _cg(self, A: LinearOperator, M: BlockJacobi, b: wp.array, x: wp.array, rtol: float, maxiter: int,
            exact_below: float, refine_above: float = 0.0, tight: float | None = None) -> tuple[CgResult, int]:
        """CG on A x = (I - P) b (P: the fixed components) from x = 0, to ``rtol``, then on from there to ``tight``
        (default ``cg_tol``) where ``refine_above`` <= max |x| < ``exact_below`` (mm): (the last solve's result,
        iterations of both). The
        CG's graph takes b and sets x = 0 itself (definite_cg.py ``fixed``; b is the caller's kept array). Not converged
        also where A is found not to be positive definite (definite_cg.py; ``not_definite`` counts those; a NaN stops it
        the same way)."""
        work = self._device_work()
        coarse = work.coarse if work.coarse is not None and work.coarse.ready else None
        result = definite_cg(A, b, x, rtol, maxiter, M, workspace=work.cg, coarse=coarse, fixed=self._fixed,
                             from_zero=True)
        total = result.iterations
        tight = tight or self.cg_tol
        if result.converged and rtol > tight and refine_above <= result.x_max < exact_below:
            result = definite_cg(A, b, x, tight, self.cg_maxiter, M, workspace=work.cg, coarse=coarse,
                                 fixed=self._fixed)
            total += result.iterations
        self.not_definite += result.not_definite
        return result, total

    def _known_solution(self, x: wp.array, result: CgResult) -> wp.array:
        """A copy of the CG's solution ``x`` in the next of the ``SOLUTIONS`` kept arrays, kept for ``known_summary``
        with the (x . b, max |x|, finite) that the CG read with its state (``result``)."""
        work = self._device_work()
        out = work.solutions[work.next_solution]  # a row: a view of the kept array
        work.next_solution = (work.next_solution + 1) % work.solutions.shape[0]
        wp.copy(out, x)
        self._known = (out, (result.x_dot_b, result.x_max,
                             bool(np.isfinite(result.x_max) and np.isfinite(result.x_dot_b))))
        return out

    def solution_row(self, x: wp.array) -> tuple[wp.array, int] | None:
        """(the kept solutions, (SOLUTIONS, nodes) vec3d, and x's row in them) where ``x`` is one of the device
        solutions this solver returned (valid as ``SOLUTIONS`` says), else None: lets a caller's CUDA graph read
        whichever of them it is given at its replay (trial_point.py ``_try_step``)."""
        solutions = self._work.solutions if self._work is not None else None
        if solutions is None or x.device != solutions.device or x.dtype != solutions.dtype \
                or x.shape != solutions.shape[1:] or x.strides != solutions.strides[1:]:
            return None
        offset, row_bytes = x.ptr - solutions.ptr, solutions.strides[0]
        if offset < 0 or offset % row_bytes or offset // row_bytes >= solutions.shape[0]:
            return None
        return solutions, offset // row_bytes

    def _solve_cg(self, H: BsrMatrix, rhs: wp.array, rtol: float, exact_below: float,
                  coarse_from_this: bool = True, single_precision: bool = True,
                  tight: float | None = None) -> wp.array | None:
        """CG on the device (``_cg``; ``tight`` as there) in at most ``cg_maxiter`` iterations; None if it did not
        converge (rhs is left as it was; H is projected in place, and projecting it again changes nothing). With
        ``coarse_from_this``, the first system of a load step that converges makes the coarse inverse (coarse_space.py)
        for the systems after it. ``single_precision``: the product reads H rounded to float32 (else H itself)."""
        key = (H.offsets.ptr, H.columns.ptr, H.row_counts.ptr if H.row_counts else 0, H.nrow)
        if self._fixed_blocks is None or self._fixed_blocks[0] != key:  # once per sparsity: the solver keeps its matrix
            self._fixed_blocks = (key, *fixed_blocks(H, self._fixed.numpy() > 0.5))
        work = self._device_work()
        if len(work.rounded) < len(H.values):  # the float32 blocks' buffer, grown to the matrix's capacity
            work.rounded = wp.empty(len(H.values), dtype=wp.mat33f, device=self.device)
        fixed_blocks_ = self._fixed_blocks[1:]

        def prologue() -> None:  # H projected, rounded and its diagonal inverted: one graph (replay.py)
            project_fixed(H, self._fixed, fixed_blocks_)
            if single_precision:
                round_to_float32(H, work.rounded)
            invert_diagonal(H, work.inverse)

        work.graphs.run(("prologue", *key, H.values.ptr, len(H.values), *(a.ptr for a in fixed_blocks_),
                         work.rounded.ptr, single_precision),
                        (H.offsets, H.columns, H.row_counts, H.values, *fixed_blocks_, work.rounded), prologue)
        A = block_row_operator(H, single_precision=True, rounded=work.rounded, round_now=False) if single_precision \
            else block_row_operator(H)
        M = BlockJacobi(H, inverse=work.inverse, invert_now=False)
        result, self.last_iterations = self._cg(A, M, rhs, work.x, rtol, self.cg_maxiter, exact_below, tight=tight)
        if not result.converged:
            return None
        self._converged_iterations = self.last_iterations
        self._last_cg = (A, M)
        if work.coarse is not None and coarse_from_this and not self._coarse_tried and (
                not work.coarse.ready or self._steps_since_coarse >= COARSE_REFRESH_STEPS):
            self._coarse_tried = True
            if work.coarse.update(H):
                self._steps_since_coarse = 0
        return self._known_solution(work.x, result)  # a copy: the kept x is the next solve's
