"""The reference for the device CG's iterates (physics/definite_cg.py): preconditioned CG from 0 in numpy, the
recurrence of definite_cg.py's docstring."""

import numpy as np
import scipy.sparse as sp


def diagonal_block_inverses(A: sp.csr_matrix) -> np.ndarray:
    """The inverses of A's 3x3 diagonal blocks (n, 3, 3): block-Jacobi."""
    n = A.shape[0] // 3
    return np.linalg.inv(np.stack([A[3 * i:3 * i + 3, 3 * i:3 * i + 3].toarray() for i in range(n)]))


def pcg_iterate(A: sp.csr_matrix, b: np.ndarray, precondition, iterations: int) -> np.ndarray:
    """x after ``iterations`` steps of PCG from 0 with z = precondition(r)."""
    x, r = np.zeros_like(b), b.copy()
    z = precondition(r)
    p, rz = z.copy(), r @ z
    for _ in range(iterations):
        q = A @ p
        alpha = rz / (p @ q)
        x, r = x + alpha * p, r - alpha * q
        z = precondition(r)
        rz, rz_old = r @ z, rz
        p = z + rz / rz_old * p
    return x
