"""The host (direct) path's pieces for linear.py: a sparse Cholesky (CHOLMOD) or LU (SuperLU) factorisation of the
free-dof Hessian, conjugate gradients preconditioned with a kept factorisation (``pcg``), on scipy matrices, and
``bsr_to_scipy`` (a Warp block matrix as a scipy one)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from warp.sparse import BsrMatrix


def bsr_to_scipy(A: BsrMatrix) -> sp.csr_matrix:
    nnz = int(A.offsets.numpy()[-1])
    bs = A.block_shape
    values = A.values.numpy()[:nnz].reshape(nnz, *bs)
    M = sp.bsr_matrix((values, A.columns.numpy()[:nnz], A.offsets.numpy()), shape=A.shape)
    return M.tocsr()


class Factor:
    """A factorisation of the free-dof Hessian: ``solve(b)``, ``shape`` and which library made it."""

    def __init__(self, solve, shape, kind: str):
        self.solve, self.shape, self.kind = solve, shape, kind


def cholmod_module():
    """scikit-sparse's CHOLMOD module, or None where it is not installed (e.g. the GPU bundle)."""
    try:
        from sksparse import cholmod
    except ImportError:
        return None
    return cholmod


def factorise(A: sp.csc_matrix, definite: bool = False, symbolic=None) -> Factor | None:
    """Factorises the (symmetric, normally positive definite) free-dof Hessian; with ``definite``, None where
    CHOLMOD finds it is not positive definite (the caller then tries a Hessian that is).

    CHOLMOD's supernodal Cholesky (scikit-sparse) when installed: for P2 meshes of 10^4-10^5 dofs it is an
    order of magnitude faster than SuperLU. ``symbolic``: a CHOLMOD analysis (fill-reducing ordering and the
    factor's structure) of a pattern that contains A's; only the numeric factorisation is then done (the
    ordering was half of each factorisation: 186 of 350 ms on the tiny press fixture's 13.6k dofs). Otherwise, or
    if the matrix is not positive definite, SuperLU: first without partial pivoting (DiagPivotThresh 0, keeps the
    symmetric minimum-degree ordering: about half the fill of threshold pivoting), then, if that breaks down (a
    tiny pivot of an indefinite matrix: non-finite or inaccurate result), with pivoting."""
    cholmod = cholmod_module()
    if cholmod is not None:
        try:
            factor = symbolic.cholesky(A) if symbolic is not None else cholmod.cholesky(A)
            return Factor(factor.solve_A, A.shape, "cholmod")
        except cholmod.CholmodNotPositiveDefiniteError:
            if definite:
                return None
    b = A @ np.ones(A.shape[0])
    try:
        lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True, "DiagPivotThresh": 0.0})
        x = lu.solve(b)
        if np.all(np.isfinite(x)) and np.max(np.abs(x - 1.0)) <= 1.0e-6:
            return Factor(lu.solve, A.shape, "superlu")
    except RuntimeError:  # exactly singular pivot
        pass
    lu = spla.splu(A, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
    return Factor(lu.solve, A.shape, "superlu-pivoting")


def sparsity_pattern(A: sp.spmatrix) -> sp.csc_matrix:
    """A's stored entries (explicit zeros too) as a matrix of ones."""
    P = sp.csc_matrix(A, copy=True)
    P.data[:] = 1.0
    return P


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """Inner product without BLAS: numpy's threaded ddot (n > 10^4) leaves its OpenBLAS threads spinning,
    and the CHOLMOD solve that follows (another OpenBLAS, on the same cores) then took 0.11 s instead of
    0.007 s on the 2-core CPU (13k dofs)."""
    return float(np.add.reduce(a * b))


#: ``pcg`` gives up from this iteration on where its mean rate so far would need over 1.5 x its iteration cap
PCG_RATE_CHECK = 6


def pcg(A: sp.csc_matrix, b: np.ndarray, M, rtol: float, maxiter: int,
        x0: np.ndarray | None = None) -> tuple[np.ndarray | None, int]:
    """Conjugate gradients preconditioned by ``M`` (a solve with an earlier factorisation), from ``x0`` (default 0);
    (x, iterations) once |b - A x| <= rtol |b|, (None, iterations) if not within ``maxiter`` iterations, if A
    is not positive definite along ``x0`` or a search direction, or, from iteration ``PCG_RATE_CHECK`` on, where the mean
    residual reduction per iteration so far, (|r_k| / |b|)^(1/k), would need more than 1.5 ``maxiter`` iterations to
    reach rtol. The caller then factorises the matrix anew; on the tiny press fixture (2-core CPU) the kept
    factorisation's PCG that fails runs its whole cap of 20 iterations before the matrix is
    factorised anyway; with this test ``solve`` took 160 instead of 173 ms per call (scripts/fem_phase_profile.py)."""
    if x0 is None or not np.any(x0):
        x, r = np.zeros_like(b), b.copy()
    else:  # a start that is returned as it is (within rtol) must not hide a matrix that is not positive definite
        x = x0.copy()
        Ax = A @ x
        if not _dot(x, Ax) > 0.0:
            return None, 0
        r = b - Ax
    b_norm = np.sqrt(_dot(b, b))
    stop = rtol * b_norm
    if np.sqrt(_dot(r, r)) <= stop:
        return x, 0
    z = M(r)
    p = z.copy()
    rz = _dot(r, z)
    for k in range(1, maxiter + 1):
        Ap = A @ p
        pAp = _dot(p, Ap)
        if not pAp > 0.0:
            return None, k
        alpha = rz / pAp
        x += alpha * p
        r -= alpha * Ap
        r_norm = np.sqrt(_dot(r, r))
        if r_norm <= stop:
            return (x, k) if np.all(np.isfinite(x)) else (None, k)
        if k >= PCG_RATE_CHECK and not k * np.log(rtol) / np.log(min(r_norm / b_norm, 1.0 - 1e-12)) <= 1.5 * maxiter:
            return None, k
        z = M(r)
        rz_new = _dot(r, z)
        p = z + (rz_new / rz) * p
        rz = rz_new
    return None, maxiter
