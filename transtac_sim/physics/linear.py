"""Linear solves for the Newton steps: H du = -g with some degrees of freedom fixed (du = 0 there).

- ``"direct"``: a sparse Cholesky (CHOLMOD) or LU (SuperLU) factorisation on the host, on the free
  rows/columns only (host_factorisation.py). Fastest on the CPU for the mesh sizes used here. The factorisation
  is kept: later Newton steps are solved by conjugate gradients preconditioned with it, to Newton's forcing term
  (inexact Newton, as on the device: loose far from the solution, ``cg_tol`` near it), from the step estimate where
  Newton has one (``guess``), and the matrix is factorised again only when that does not converge in
  ``reuse_max_iterations`` (or its rate shows by iteration ``PCG_RATE_CHECK`` that it will not). With the forcing term
  instead of 1e-6 for every system, and Newton's estimate changes (newton.py), the tiny press fixture's frames 0-1 take 4
  factorisations instead of 8 (2-core CPU, scripts/fem_phase_profile.py; BENCHMARKS.md ``fem_host_inexact_newton_cpu``).
  The numeric factorisation runs on the BLAS threads the process has (the solves on one: see
  ``_solve_direct``). ``solve(..., definite=True)`` returns None instead of an LU solve where CHOLMOD
  finds the matrix is not positive definite (Newton then takes the clamped Hessian, see newton.py).
- ``"cg"``: conjugate gradients on the solver's device (the GPU path), preconditioned with block-Jacobi plus a coarse
  correction on rigid-body modes of aggregates of nodes (coarse_space.py; its inverse made from the first converged
  system and again every ``COARSE_REFRESH_STEPS`` load steps; press_slide on an H100: 0.43x the CG iterations, 0.69x
  the CG's time, BENCHMARKS.md ``fem_coarse_level_gpu``), stopping
  where the matrix is found not to be positive definite (definite_cg.py; ``solve(..., definite=True)`` then
  returns None), its matrix-vector product one warp per block row on the matrix rounded to float32 (sparse_product.py:
  half the bytes of the product that is most of CG's time); the fixed rows/columns are
  projected out in place (``_project_fixed_blocks``, on the blocks it changes). Its relative tolerance is Newton's
  forcing term (inexact Newton: loose far from the solution, tight near it). The tight tolerance ``cg_tol`` (of both
  paths) is a relative residual of 1e-4, not 1e-8: near convergence it only has to tell whether the Newton step is
  below newton_tol_mm, and on
  press_slide (H100, BENCHMARKS.md ``fem_cg_tolerance_gpu``) 1e-4 moved the markers by at most 2.1e-7 mm and the
  forces by nothing in the printed digits, with 39 % fewer CG iterations and 1.3x faster frames. The price: at 1e-4
  a CG step can be 10-50 % shorter than the exact one (scripts/bench_linear_solvers.py, ``linear_solvers_gpu``), so
  a converged step may be up to about twice newton_tol_mm (2e-5 mm by default). Where the last Hessian Newton tries
  (``definite=False``) is not solved either (CG stops at non-positive curvature or at ``cg_maxiter``), the system is
  shifted in place, H + lambda |diag(H)| (Levenberg-Marquardt, ``SHIFTS``: towards a scaled gradient step, always a
  descent direction), and solved again on the device; ``shifted_solves`` counts them and ``last_shift`` tells Newton
  that the step is not a Newton step. The device path never hands a system to the host: a host factorisation of a
  10^5-dof P2 system takes seconds with CHOLMOD and, where CHOLMOD is missing (the GPU bundle), SuperLU did not finish
  within minutes, which is what stalled train_random sequences 9 and 17 in ``generate`` on an H100 (BENCHMARKS.md
  ``fem_device_last_resort_gpu``). The last converged system's float32 matrix and
  preconditioner are kept for ``solve_last`` (in ``DeviceWork``, with the CG's arrays and graph). Warp's FSAI halves
  CG's iterations too, but its set-up (60 ms to 4 s on a 10^5-dof Newton system, H100) is made per system and costs
  more than it saves (scripts/bench_linear_solvers.py, BENCHMARKS.md ``linear_solvers_gpu``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import warp as wp
from threadpoolctl import ThreadpoolController
from warp.optim.linear import LinearOperator
from warp.sparse import BsrMatrix

from transtac_sim.physics.coarse_space import CoarseSpace
from transtac_sim.physics.definite_cg import BlockJacobi, CgWorkspace, definite_cg
from transtac_sim.physics.host_factorisation import cholmod_module, factorise, pcg, sparsity_pattern
from transtac_sim.physics.sparse_product import block_row_operator, diagonal_block


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


@wp.kernel(enable_backward=False)
def _free_part(v: wp.array(dtype=wp.vec3d), fixed: wp.array(dtype=wp.vec3d), out: wp.array(dtype=wp.vec3d)):
    """(I - P) v: v with its fixed components set to 0."""
    i = wp.tid()
    f = fixed[i]
    out[i] = wp.cw_mul(v[i], wp.vec3d(wp.float64(1.0) - f[0], wp.float64(1.0) - f[1], wp.float64(1.0) - f[2]))


#: lambda of the device's last resort, H + lambda |diag(H)|, tried in turn; at 100 the block-Jacobi-preconditioned
#: system is close to the identity and CG converges in a few iterations
SHIFTS = (1.0e-2, 1.0, 1.0e2)


#: the direct path's step estimate (``solve_last``) is solved to this relative residual first, and on to the one asked
#: for only where it is below ``exact_below`` (where the caller's convergence test reads its length): on the tiny
#: press fixture (2-core CPU) 24 instead of 31 ms per estimate, the same Newton iterations and forces
ESTIMATE_RTOL = 1.0e-2


#: the device CG's coarse inverse (coarse_space.py) is made from the first converged system of the solver, then again
#: every this many load steps: making it (the Galerkin operator's atomic sums on the device, a Cholesky inverse of about
#: 1,000 unknowns on the host) costs about as much as a few CG solves, and one made a few frames earlier serves nearly as
#: well
COARSE_REFRESH_STEPS = 10


@dataclass
class DeviceWork:
    """What the device path keeps between solves, so that each solve finds the arrays of the last and its CG can launch
    the graph captured then (definite_cg.py): the CG's workspace, x, the block-Jacobi inverses, the matrix's float32
    blocks (grown to the largest matrix) and the coarse level of the two-level preconditioner (None: block-Jacobi
    alone)."""

    cg: CgWorkspace
    x: wp.array
    inverse: wp.array
    rounded: wp.array
    coarse: CoarseSpace | None


class LinearSolver:
    """Solves H du = rhs with ``fixed`` (bool, (nodes, 3)) components of du set to 0."""

    def __init__(self, method: str, fixed: np.ndarray, device, cg_tol: float = 1.0e-4, cg_maxiter: int = 20000,
                 reuse_max_iterations: int = 20, node_positions_mm: np.ndarray | None = None,
                 coarse_cell_mm: float | None = None):
        """``node_positions_mm`` (nodes, 3) and ``coarse_cell_mm``: the device CG's coarse level (coarse_space.py;
        without them, or on the direct path, block-Jacobi alone)."""
        if method not in ("direct", "cg"):
            raise ValueError(f"unknown linear solver {method!r}")
        if coarse_cell_mm is not None and not coarse_cell_mm > 0.0:
            raise ValueError(f"coarse_cell_mm must be > 0 (or None for block-Jacobi alone), got {coarse_cell_mm}")
        self._coarse_setup = (node_positions_mm, fixed, coarse_cell_mm) \
            if method == "cg" and node_positions_mm is not None and coarse_cell_mm is not None else None
        self._coarse_tried = False  # the coarse inverse was made or tried in this load step (``new_load_step``)
        self._steps_since_coarse = 0  # load steps begun since the coarse inverse was made
        self.method = method
        self.device = device
        self.cg_tol = cg_tol
        self.cg_maxiter = cg_maxiter
        flat = fixed.reshape(-1)
        self._free = np.flatnonzero(~flat)
        self._node_count = fixed.shape[0]
        self._fixed = wp.array(fixed.astype(np.float64), dtype=wp.vec3d, device=device)  # 1 where fixed
        self.last_iterations = 0
        self.reuse_max_iterations = reuse_max_iterations
        self.factorisations = 0
        self.shifted_solves = 0  # device systems solved only with a Levenberg-Marquardt shift (``SHIFTS``)
        self.last_shift = 0.0  # the shift lambda of the last solve's result (0: a Newton step)
        self.not_definite = 0  # device solves stopped because the matrix is not positive definite
        self._lu = None
        self._last_free: sp.csc_matrix | None = None  # the last direct system's free-dof matrix
        self._free_map: tuple | None = None  # (H's block columns, gather, CSC indices, CSC indptr): ``_free_matrix``
        # CHOLMOD's analysis of the free-dof matrices' pattern (None without CHOLMOD): made on the first matrix of a
        # sparsity (``_solve_direct``); ``_free_matrix`` forgets it when the sparsity changes
        self._analysed = None
        # the host path's BLAS (numpy's, scipy's and CHOLMOD's OpenBLAS) held to one thread: see ``_solve_direct``
        self._blas: ThreadpoolController | None = None  # made on the first host solve
        self._converged_iterations = 0  # CG iterations of the last converged device solve
        self._last_cg: tuple | None = None  # the last converged device system's (operator, preconditioner)
        self._work: DeviceWork | None = None  # the device path's kept arrays (``_device_work``)
        self._fixed_blocks: tuple | None = None  # (sparsity key, blocks, rows) of ``fixed_blocks`` for the last matrix

    def new_load_step(self) -> None:
        """A new (sub)step begins: every ``COARSE_REFRESH_STEPS``-th, the device CG's coarse inverse is made again from
        its first converged system (until then the kept one serves, coarse_space.py)."""
        self._coarse_tried = False
        self._steps_since_coarse += 1

    def solve(self, H: BsrMatrix, rhs: wp.array, definite: bool = False,
              rtol: float | None = None, exact_below: float = 0.0, guess: np.ndarray | None = None) -> wp.array | None:
        """Returns du (wp.array of vec3d on the device). ``H`` is changed: its fixed rows and columns are projected out
        in place (the caller assembles it anew for each system, assembly.py). With
        ``definite``: None where H is found not to be positive definite (CHOLMOD; CG does not converge).
        ``rtol``: CG's relative residual tolerance (default ``cg_tol``; Newton passes a looser one far from
        the solution, newton.py), continued to ``cg_tol`` where the solution is below ``exact_below`` mm (an
        early-stopped CG solution is shorter than the exact one, and Newton tests convergence on its length);
        on the direct path a new factorisation solves exactly, and ``rtol`` below ``cg_tol`` is raised to it.
        ``guess`` (nodes, 3): where the direct path's PCG starts (Newton's step estimate for the same right-hand
        side; the device CG starts from 0). Without ``definite``, a system the device CG does not solve is shifted
        (``_solve_shifted``)."""
        self.forget()
        self.last_shift = 0.0
        if self.method == "direct":
            return self._solve_direct(H, rhs, definite, rtol or self.cg_tol, exact_below, guess)
        x = self._solve_cg(H, rhs, rtol or self.cg_tol, exact_below)
        if x is not None or definite:
            return x
        return self._solve_shifted(H, rhs, rtol or self.cg_tol)

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

    def _solve_direct(self, H: BsrMatrix, rhs: wp.array, definite: bool = False, rtol: float = 0.0,
                      exact_below: float = 0.0, guess: np.ndarray | None = None) -> wp.array | None:
        """The host path. Its BLAS runs on one thread: with their default thread pools, three OpenBLAS copies (numpy's,
        scipy's, CHOLMOD's) spin-wait against each other and the next Warp kernel on few cores; on the 2-core CPU
        (tiny press fixture, scripts/fem_phase_profile.py) the kept-factorisation solves took 131 ms per call
        against 38 ms on one thread, and the process 10 s of system time in 15 s. The numeric factorisation alone
        takes the process's BLAS threads (as found on the first solve: all cores, or a ``generate`` worker's share):
        on the 2-core CPU ``solve`` took 173 instead of 199 ms per call with it (tiny press fixture,
        scripts/fem_phase_profile.py)."""
        A = self._free_matrix(H)
        cholmod = cholmod_module()  # loaded before the BLAS controller below is made, so that it finds CHOLMOD's OpenBLAS
        if self._analysed is None and cholmod is not None:  # on every stored entry, zero or not: the elements'
            self._analysed = cholmod.analyze(sparsity_pattern(A))  # sparsity, which every later matrix shares
        b = rhs.numpy().reshape(-1)[self._free]
        if self._blas is None:
            self._blas = ThreadpoolController()
            self._factor_threads = min(lib["num_threads"] for lib in self._blas.select(user_api="blas").info())
        with self._blas.limit(limits=1, user_api="blas"):
            x_free = self._solve_free(A, b, definite, rtol, exact_below,
                                      None if guess is None else guess.reshape(-1)[self._free])
        if x_free is None:
            return None
        self._last_free = A
        x = np.zeros(3 * self._node_count)
        x[self._free] = x_free
        return wp.array(x.reshape(-1, 3), dtype=wp.vec3d, device=self.device)

    def _free_matrix(self, H: BsrMatrix) -> sp.csc_matrix:
        """H's free rows and columns as a CSC matrix (every stored entry, zero or not). The first call for a sparsity
        finds where each of H's stored values goes (a matrix of their indices taken through the conversion and the
        slicing); later calls, the same sparsity (assembly.py keeps it), only gather the values: on the tiny press fixture
        (13.7k dofs, 2-core CPU, ``python -m cProfile scripts/fem_frame_timing.py tests/fixtures/tiny_press.toml``) about 7 ms
        per solve against about 22 ms of conversion and slicing."""
        nnz = int(H.offsets.numpy()[-1])
        columns = H.columns.numpy()[:nnz]
        cached = self._free_map
        if cached is None or len(cached[0]) != len(columns) or not np.array_equal(cached[0], columns):
            index = sp.bsr_matrix((np.arange(1.0, 9 * nnz + 1.0).reshape(nnz, 3, 3), columns, H.offsets.numpy()),
                                  shape=H.shape)
            picked = index.tocsr()[self._free][:, self._free].tocsc()
            picked.sort_indices()
            cached = self._free_map = (columns.copy(), picked.data.astype(np.int64) - 1, picked.indices, picked.indptr)
            self._analysed = None  # made again for this sparsity
        _, gather, indices, indptr = cached
        data = H.values.numpy().reshape(-1)[gather]
        return sp.csc_matrix((data, indices, indptr), shape=(len(self._free), len(self._free)))

    def _solve_free(self, A: sp.csc_matrix, b: np.ndarray, definite: bool = False, rtol: float = 0.0,
                    exact_below: float = 0.0, x0: np.ndarray | None = None) -> np.ndarray | None:
        """The free dofs' solution: PCG with the kept factorisation from ``x0`` to ``rtol`` (on to ``cg_tol`` where
        it is below ``exact_below`` mm), else a new factorisation's exact solve (None: not positive definite, with
        ``definite``)."""
        if self._lu is not None and self._lu.shape == A.shape:
            x, iterations = self._kept_pcg(A, b, max(rtol, self.cg_tol), self.cg_tol, exact_below, x0)
            if x is not None:
                self.last_iterations = iterations
                return x
        with self._blas.limit(limits=self._factor_threads, user_api="blas"):
            factor = factorise(A, definite, self._analysed)
        self.factorisations += 1
        if factor is None:
            return None
        self._lu = factor
        self.last_iterations = 1
        return self._lu.solve(b)

    def _kept_pcg(self, A: sp.csc_matrix, b: np.ndarray, loose: float, tight: float, exact_below: float,
                  x0: np.ndarray | None = None) -> tuple[np.ndarray | None, int]:
        """PCG with the kept factorisation from ``x0`` to ``loose``, then on to ``tight`` where the solution is below
        ``exact_below`` mm: (x or None, iterations)."""
        x, iterations = pcg(A, b, self._lu.solve, loose, self.reuse_max_iterations, x0)
        if x is not None and loose > tight and np.max(np.abs(x)) < exact_below:
            x, more = pcg(A, b, self._lu.solve, tight, self.reuse_max_iterations, x)
            iterations += more
        return x, iterations

    def solve_last(self, rhs: np.ndarray, rtol: float = 1.0e-3, exact_below: float = 0.0) -> np.ndarray | None:
        """The last system's matrix solved for another right-hand side ``rhs`` (nodes, 3; 0 on the fixed
        components), without assembly or factorisation: by CG preconditioned with the kept factorisation (direct
        path: to ``ESTIMATE_RTOL``, then on to ``rtol`` where the solution is below ``exact_below`` mm) or with the
        kept block-Jacobi preconditioner on the device (CG path: to ``rtol``, then on to ``cg_tol`` where the solution
        is below ``exact_below`` mm), because an early-stopped CG solution is shorter than the exact one and the caller
        tests convergence on it. (nodes, 3) with 0 on the fixed components, or None (no system yet, or no
        convergence within the iterations allowed)."""
        if self.method == "cg":
            return self._solve_last_cg(rhs, rtol, exact_below)
        if self._last_free is None or self._lu is None or self._lu.shape != self._last_free.shape:
            return None
        b = rhs.reshape(-1)[self._free]
        with self._blas.limit(limits=1, user_api="blas"):
            x, _ = self._kept_pcg(self._last_free, b, max(rtol, ESTIMATE_RTOL), rtol, exact_below)
        if x is None:
            return None
        out = np.zeros(3 * self._node_count)
        out[self._free] = x
        return out.reshape(-1, 3)

    def _solve_last_cg(self, rhs: np.ndarray, rtol: float, exact_below: float) -> np.ndarray | None:
        if self._last_cg is None:
            return None
        A, M = self._last_cg
        b = wp.array(np.asarray(rhs).reshape(-1, 3), dtype=wp.vec3d, device=self.device)
        x = self._device_work().x
        x.zero_()
        converged, _ = self._cg(A, M, b, x, rtol, max(50, self._converged_iterations), exact_below)
        return x.numpy() if converged else None

    def _device_work(self) -> DeviceWork:
        """The device path's arrays kept between solves (made on first use)."""
        if self._work is None:
            coarse = CoarseSpace(*self._coarse_setup, self.device) if self._coarse_setup is not None else None
            self._work = DeviceWork(CgWorkspace(self._node_count, self.device),
                                    wp.empty(self._node_count, dtype=wp.vec3d, device=self.device),
                                    wp.empty(self._node_count, dtype=wp.mat33d, device=self.device),
                                    wp.empty(0, dtype=wp.mat33f, device=self.device), coarse)
        return self._work

    def coarse_stats(self) -> dict[str, int]:
        """The coarse level's size and how often its inverse was made or refused (empty without one)."""
        coarse = self._work.coarse if self._work is not None else None
        if coarse is None:
            return {}
        return {"coarse_unknowns": coarse.size, "coarse_updates": coarse.updates, "coarse_rejected": coarse.rejected,
                **{f"coarse_{k}_s": round(v, 3) for k, v in coarse.seconds.items()}}

    def _cg(self, A: LinearOperator, M: BlockJacobi, b: wp.array, x: wp.array, rtol: float, maxiter: int,
            exact_below: float) -> tuple[bool, int]:
        """CG on A x = b from x, to ``rtol``, then on from there to ``cg_tol`` where max |x| < ``exact_below``:
        (converged, iterations). Not converged also where A is found not to be positive definite (definite_cg.py;
        ``not_definite`` counts those; a NaN stops it the same way)."""
        work = self._device_work()
        coarse = work.coarse if work.coarse is not None and work.coarse.ready else None
        result = definite_cg(A, b, x, rtol, maxiter, M, workspace=work.cg, coarse=coarse)
        total = result.iterations
        if result.converged and rtol > self.cg_tol and exact_below > 0.0 \
                and float(np.max(np.abs(x.numpy()))) < exact_below:
            result = definite_cg(A, b, x, self.cg_tol, self.cg_maxiter, M, workspace=work.cg, coarse=coarse)
            total += result.iterations
        self.not_definite += result.not_definite
        return result.converged, total

    def forget(self) -> None:
        """The next ``solve_last`` returns None until a new system is solved (e.g. the energy has changed)."""
        self._last_free = None
        self._last_cg = None

    def _solve_cg(self, H: BsrMatrix, rhs: wp.array, rtol: float, exact_below: float,
                  coarse_from_this: bool = True) -> wp.array | None:
        """CG on the device (``_cg``) in at most ``cg_maxiter`` iterations; None if it did not converge (rhs is
        left as it was; H is projected in place). With ``coarse_from_this``, the first system of a load step that
        converges makes the coarse inverse (coarse_space.py) for the systems after it."""
        key = (H.offsets.ptr, H.columns.ptr, H.row_counts.ptr if H.row_counts else 0, H.nrow)
        if self._fixed_blocks is None or self._fixed_blocks[0] != key:  # once per sparsity: the solver keeps its matrix
            self._fixed_blocks = (key, *fixed_blocks(H, self._fixed.numpy() > 0.5))
        project_fixed(H, self._fixed, self._fixed_blocks[1:])
        b = wp.empty_like(rhs)
        wp.launch(_free_part, dim=len(b), device=self.device, inputs=[rhs, self._fixed, b])
        work = self._device_work()
        if len(work.rounded) < len(H.values):  # the float32 blocks' buffer, grown to the matrix's capacity
            work.rounded = wp.empty(len(H.values), dtype=wp.mat33f, device=self.device)
        A = block_row_operator(H, single_precision=True, rounded=work.rounded)
        M = BlockJacobi(H, inverse=work.inverse)
        work.x.zero_()
        converged, self.last_iterations = self._cg(A, M, b, work.x, rtol, self.cg_maxiter, exact_below)
        if not converged:
            return None
        self._converged_iterations = self.last_iterations
        self._last_cg = (A, M)
        if work.coarse is not None and coarse_from_this and not self._coarse_tried and (
                not work.coarse.ready or self._steps_since_coarse >= COARSE_REFRESH_STEPS):
            self._coarse_tried = True
            if work.coarse.update(H):
                self._steps_since_coarse = 0
        return wp.clone(work.x)  # the kept x is the next solve's
