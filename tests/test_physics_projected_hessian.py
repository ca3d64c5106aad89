"""The projected volumetric Hessian (volumetric_hessian.py ``projected_density_hessian``): its eigen-decomposition of
d^2 Psi / dF^2 against a finite-difference Hessian in numpy, its filter, and the assembled Newton Hessian it gives."""

import numpy as np
import pytest
import warp as wp
from test_physics_barrier import _compressed, _far_away, _solver  # noqa: I001

from transtac_sim.physics import SolverSettings
from transtac_sim.physics.elasticity import EXACT, PROJECTED
from transtac_sim.physics.host_factorisation import bsr_to_scipy
from transtac_sim.physics.volumetric_hessian import _mat99, projected_density_hessian


@wp.kernel
def _projected(F: wp.array(dtype=wp.mat33d), lam: wp.float64, s: wp.array(dtype=wp.float64), floor: wp.float64,
               out: wp.array(dtype=_mat99)):
    i = wp.tid()
    out[i] = projected_density_hessian(F[i], lam, s[i], floor)


def _density_hessian(F: np.ndarray, lam: float, alpha: float) -> tuple[np.ndarray, float]:
    """d^2 Psi / dF^2 of Psi = lam/2 (det F - alpha)^2 (9x9, vec row by row) by central differences of its gradient
    lam (J - alpha) cof F, and s = lam (J - alpha)."""
    def gradient(G):
        return (lam * (np.linalg.det(G) - alpha) * np.linalg.det(G) * np.linalg.inv(G).T).reshape(-1)
    h = 1e-6
    H = np.empty((9, 9))
    for k in range(9):
        E = np.zeros(9)
        E[k] = h
        H[:, k] = (gradient(F + E.reshape(3, 3)) - gradient(F - E.reshape(3, 3))) / (2 * h)
    return 0.5 * (H + H.T), lam * (np.linalg.det(F) - alpha)


def _states(count: int, seed: int = 0):
    """Random F with det F > 0: stretched, compressed (det F down to 0.05), sheared and rotated."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
        Q *= np.sign(np.linalg.det(Q))
        F = Q @ np.diag(rng.uniform(0.3, 1.4, 3)) @ (np.eye(3) + 0.3 * rng.standard_normal((3, 3)))
        if np.linalg.det(F) > 0.05:
            yield F


@pytest.mark.parametrize("floor", [1e4, 0.2, 0.0])
def test_projected_density_hessian_is_the_filtered_exact_one(floor):
    """With a floor that no eigenvalue reaches the projection returns d^2 Psi / dF^2 itself (so the 9 modes are its
    eigenvectors); with floor m the eigenvalues of H' + m I are those of |H + m I|, eigenvector by eigenvector."""
    lam, alpha = 5.0, 1.0 + 0.1 / 5.0
    Fs = list(_states(40))
    exact = [_density_hessian(F, lam, alpha) for F in Fs]
    out = wp.zeros(len(Fs), dtype=_mat99, device="cpu")
    wp.launch(_projected, dim=len(Fs), device="cpu",
              inputs=[wp.array(np.stack(Fs), dtype=wp.mat33d, device="cpu"), lam,
                      wp.array([s for _, s in exact], dtype=wp.float64, device="cpu"), floor, out])
    flipped = 0
    for (H, _), P in zip(exact, out.numpy(), strict=True):
        scale = np.abs(H).max()
        if floor > 1e3:
            np.testing.assert_allclose(P, H, atol=1e-6 * scale)
            continue
        w, Q = np.linalg.eigh(H + floor * np.eye(9))
        expected = Q @ np.diag(np.abs(w)) @ Q.T - floor * np.eye(9)
        np.testing.assert_allclose(P, expected, atol=1e-6 * scale)
        flipped += np.any(w < 0.0)
    if floor <= 1e3:
        assert flipped >= 10  # the filter acts in many of these states


@pytest.mark.parametrize("squeeze", [0.2, 0.08, 0.03])
def test_projected_hessian_is_positive_definite_and_exact_in_tension(squeeze):
    """Newton's second Hessian (the projected one) on the free dofs is positive definite in compression, also where
    the barrier acts (squeeze 0.08, 0.03), where the exact Hessian is not; in a slight stretch, where no eigenvalue is
    below the floor, it is the exact one. (In compression the volumetric pressure lam (J - alpha) is below -mu, and the
    twist modes mu + s sigma_k, which are the rotations' zero at rest, go negative tet by tet: the projection acts
    there at any strain.)"""
    solver = _solver(SolverSettings())
    ind = _far_away(solver)
    free = ~solver._fixed_nodes.reshape(-1)

    def hessian(filtering):
        return bsr_to_scipy(solver._hessian(ind, geometric=1.0, clamp=filtering)).toarray()[free][:, free]

    solver.u.dof_values.assign(wp.array(_compressed(solver, squeeze), dtype=wp.vec3d))
    solver._gradient(ind)
    H = hessian(PROJECTED)
    ev = np.linalg.eigvalsh(0.5 * (H + H.T))
    assert ev[0] > 1e-4 * ev[-1]
    assert np.linalg.eigvalsh(hessian(EXACT))[0] < 0.0

    solver.u.dof_values.assign(wp.array(_compressed(solver, 1.02), dtype=wp.vec3d))
    solver._gradient(ind)
    exact = hessian(EXACT)
    np.testing.assert_allclose(hessian(PROJECTED), exact, atol=1e-9 * np.abs(exact).max())
