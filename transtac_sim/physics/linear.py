"""Linear solves for the Newton steps: H du = -g with some degrees of freedom fixed (du = 0 there).

- ``"direct"``: a sparse Cholesky (CHOLMOD) or LU (SuperLU) factorisation on the host, on the free
  rows/columns only (host_factorisation.py). Fastest on the CPU for the mesh sizes used here. The factorisation
  is kept: later Newton steps are solved by conjugate gradients preconditioned with it, to Newton's forcing term
  (inexact Newton, as on the device: loose far from the solution, ``cg_tol`` near it or the caller's ``tight``), from
  the step estimate where
  Newton has one (``guess``), and the matrix is factorised again only when that does not converge in
  ``reuse_max_iterations`` (or its rate shows by iteration ``PCG_RATE_CHECK`` that it will not). With the forcing term
  instead of 1e-6 for every system, and Newton's estimate changes (newton.py), the tiny press fixture's frames 0-1 take 4
  factorisations instead of 8 (2-core CPU, scripts/fem_phase_profile.py; BENCHMARKS.md ``fem_host_inexact_newton_cpu``).
  The numeric factorisation runs on the BLAS threads the process has (the solves on one: see
  ``_solve_direct``). ``solve(..., definite=True)`` returns None instead of an LU solve where CHOLMOD
  finds the matrix is not positive definite (Newton then takes the clamped Hessian, see newton.py).
- ``"cg"``: conjugate gradients on the solver's device (the GPU path): device_linear.py.

The tight tolerance ``cg_tol`` of both paths is a relative residual of 1e-4 (see device_linear.py for why).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import warp as wp
from threadpoolctl import ThreadpoolController
from warp.sparse import BsrMatrix

from transtac_sim.physics.device_linear import DeviceSolves, DeviceWork
from transtac_sim.physics.host_factorisation import cholmod_module, factorise, pcg, sparsity_pattern

#: the direct path's step estimate (``solve_last``) is solved to this relative residual first, and on to the one asked
#: for only where its length is within [``refine_above``, ``exact_below``) (where the caller's comparison with a
#: threshold could go either way, friction_lag.py ``_estimate_band``): on the tiny press fixture (2-core CPU) 24
#: instead of 31 ms per estimate, the same Newton iterations and forces
ESTIMATE_RTOL = 1.0e-2


class LinearSolver(DeviceSolves):
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
        self.float64_solves = 0  # device systems solved with the float64 product after the float32 one refused them
        self.estimate_iterations = 0  # device CG iterations of the step estimates (``solve_last``)
        self.estimates_unconverged = 0  # device step estimates that did not converge (None returned)
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
        # (the last solution returned on the device path, its (x . b, max |x|, finite) read with the CG's state)
        self._known: tuple | None = None
        self._fixed_blocks: tuple | None = None  # (sparsity key, blocks, rows) of ``fixed_blocks`` for the last matrix

    def new_load_step(self) -> None:
        """A new (sub)step begins: every ``COARSE_REFRESH_STEPS``-th, the device CG's coarse inverse is made again from
        its first converged system (until then the kept one serves, coarse_space.py)."""
        self._coarse_tried = False
        self._steps_since_coarse += 1

    def solve(self, H: BsrMatrix, rhs: wp.array, definite: bool = False,
              rtol: float | None = None, exact_below: float = 0.0, guess: wp.array | None = None,
              tight: float | None = None) -> wp.array | None:
        """Returns du (wp.array of vec3d on the device; on the CG path one of device_linear.SOLUTIONS kept arrays,
        overwritten by the SOLUTIONS-th solution returned after it). ``H`` is changed: its fixed rows and columns are
        projected out in place (the caller assembles it anew for each system, hessian_assembly.py). With
        ``definite``: None where H is found not to be positive definite (CHOLMOD; CG does not converge).
        ``rtol``: CG's relative residual tolerance (default ``cg_tol``; Newton passes a looser one far from
        the solution, newton.py), continued to ``tight`` where the solution is below ``exact_below`` mm (an
        early-stopped CG solution is shorter than the exact one, and Newton tests convergence on its length).
        ``tight``: ``cg_tol`` by default, or a looser tolerance where the caller needs no more (convergence_tests.py
        ``_force_forcing``); never below ``cg_tol``. On the direct path a new factorisation solves exactly, and
        ``rtol`` below ``tight`` is raised to it (Newton never passes one).
        ``guess`` (vec3d per node): where the direct path's PCG starts (Newton's step estimate for the same right-hand
        side; the device CG starts from 0). Without ``definite``, a system the device CG refuses as not positive
        definite with the float32 product is solved with the float64 one, and one it does not solve is shifted
        (``_solve_shifted``; device_linear.py)."""
        self.forget()
        self.last_shift = 0.0
        tight = max(tight or 0.0, self.cg_tol)
        if self.method == "direct":
            return self._solve_direct(H, rhs, definite, rtol or self.cg_tol, exact_below, guess, tight)
        refused = self.not_definite
        x = self._solve_cg(H, rhs, rtol or self.cg_tol, exact_below, tight=tight)
        if x is not None or definite:
            return x
        if self.not_definite > refused:  # the float32 product found it not positive definite: try the float64 one
            x = self._solve_cg(H, rhs, rtol or self.cg_tol, exact_below, single_precision=False, tight=tight)
            if x is not None:
                self.float64_solves += 1
                return x
        return self._solve_shifted(H, rhs, rtol or self.cg_tol)

    def _solve_direct(self, H: BsrMatrix, rhs: wp.array, definite: bool = False, rtol: float = 0.0,
                      exact_below: float = 0.0, guess: wp.array | None = None,
                      tight: float | None = None) -> wp.array | None:
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
                                      None if guess is None else guess.numpy().reshape(-1)[self._free], tight)
        if x_free is None:
            return None
        self._last_free = A
        x = np.zeros(3 * self._node_count)
        x[self._free] = x_free
        return wp.array(x.reshape(-1, 3), dtype=wp.vec3d, device=self.device)

    def _free_matrix(self, H: BsrMatrix) -> sp.csc_matrix:
        """H's free rows and columns as a CSC matrix (every stored entry, zero or not). The first call for a sparsity
        finds where each of H's stored values goes (a matrix of their indices taken through the conversion and the
        slicing); later calls, the same sparsity (hessian_assembly.py keeps it), only gather the values: on the tiny
        press fixture (13.7k dofs, 2-core CPU, ``python -m cProfile scripts/fem_frame_timing.py
        tests/fixtures/tiny_press.toml``) about 7 ms per solve against about 22 ms of conversion and slicing."""
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
                    exact_below: float = 0.0, x0: np.ndarray | None = None,
                    tight: float | None = None) -> np.ndarray | None:
        """The free dofs' solution: PCG with the kept factorisation from ``x0`` to ``rtol`` (on to ``tight``, default
        ``cg_tol``, where it is below ``exact_below`` mm), else a new factorisation's exact solve (None: not positive
        definite, with ``definite``)."""
        tight = tight or self.cg_tol
        if self._lu is not None and self._lu.shape == A.shape:
            x, iterations = self._kept_pcg(A, b, max(rtol, tight), tight, exact_below, x0)
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
                  x0: np.ndarray | None = None, refine_above: float = 0.0) -> tuple[np.ndarray | None, int]:
        """PCG with the kept factorisation from ``x0`` to ``loose``, then on to ``tight`` where max |x| (mm) is within
        [``refine_above``, ``exact_below``): (x or None, iterations)."""
        x, iterations = pcg(A, b, self._lu.solve, loose, self.reuse_max_iterations, x0)
        if x is not None and loose > tight and refine_above <= np.max(np.abs(x)) < exact_below:
            x, more = pcg(A, b, self._lu.solve, tight, self.reuse_max_iterations, x)
            iterations += more
        return x, iterations

    def solve_last(self, rhs: wp.array, rtol: float = 1.0e-3, exact_below: float = 0.0,
                   refine_above: float = 0.0) -> wp.array | None:
        """The last system's matrix solved for another right-hand side ``rhs`` (vec3d per node, on the device; 0 on the
        fixed components), without assembly or factorisation: by CG preconditioned with the kept factorisation (direct
        path: to ``ESTIMATE_RTOL``, then on to ``rtol``) or with the kept preconditioner on the device (CG path: to
        device_linear.ESTIMATE_RTOL, then on to ``cg_tol``; ``rtol`` is the direct path's only). It goes on to the
        tighter tolerance only where the loose solution's max |x| is within [``refine_above``, ``exact_below``) mm:
        an early-stopped CG solution is mostly shorter than the exact one, and the caller compares its length with a
        threshold (friction_lag.py ``_estimate_band``). An array on the device with 0 on the fixed components (on the
        CG path one of device_linear.SOLUTIONS kept arrays, overwritten by the SOLUTIONS-th solution returned after
        it), or None (no system yet, or no convergence within the iterations allowed)."""
        if self.method == "cg":
            return self._solve_last_cg(rhs, exact_below, refine_above)
        if self._last_free is None or self._lu is None or self._lu.shape != self._last_free.shape:
            return None
        b = rhs.numpy().reshape(-1)[self._free]
        with self._blas.limit(limits=1, user_api="blas"):
            x, _ = self._kept_pcg(self._last_free, b, max(rtol, ESTIMATE_RTOL), rtol, exact_below,
                                  refine_above=refine_above)
        if x is None:
            return None
        out = np.zeros(3 * self._node_count)
        out[self._free] = x
        return wp.array(out.reshape(-1, 3), dtype=wp.vec3d, device=self.device)

    def known_summary(self, x: wp.array) -> tuple[float, float, bool] | None:
        """(x . b, max |x|, whether both are finite) for ``x``, the last solution this solver returned (``solve`` or
        ``solve_last``, b its right-hand side), where the device CG read them with its state; None otherwise (the host
        path, or another array): the caller reduces them itself (reductions.py ``step_summary``, ``max_abs``). Saves
        Newton a read per step and per step estimate."""
        return self._known[1] if self._known is not None and self._known[0] is x else None

    def forget(self) -> None:
        """The next ``solve_last`` returns None until a new system is solved (e.g. the energy has changed)."""
        self._last_free = None
        self._last_cg = None

