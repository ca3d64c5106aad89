"""Stable Neo-Hookean elasticity forms for ``warp.fem`` (float64), per-tet material.

Energy of the gel, with u the displacement (mm), F = I + grad u, params (mu, lam) per tet (MPa):

    E_el(u) = sum_tets  int mu/2 (|F|^2 - 3) dV  +  int lam/2 (J - alpha)^2 dV,   alpha = 1 + mu/lam

The deviatoric-like term is integrated exactly (order 2 for P2); the volumetric term is integrated with
one point per tet (selective reduced integration). For P2 tets this is the displacement-based form of
the P2-P0 mixed element: the incompressibility constraint is imposed once per tet, so nu -> 0.5 does
not lock, while the fully integrated mu-term keeps the stiffness matrix free of spurious modes.

Gradient (N):   mu F : grad v  +  s cof(F) : grad v,          s = lam (J - alpha)
Hessian:        mu grad du : grad v + lam (cof F : grad du)(cof F : grad v) + s_h dcof(F)[grad du] : grad v
                (its volumetric part assembled tet by tet in volumetric_hessian.py; the barrier's gradient and
                Hessian: barrier_terms.py)

with cof(F) = dJ/dF = [f1 x f2, f2 x f0, f0 x f1] (columns f_i of F). ``s_h`` is ``geometric`` times
either ``s`` itself (the exact Hessian) or, with ``clamp``, ``s`` clamped to [-mu/sigma_max, mu/sigma_max]
(sigma_max the largest singular value of F); clamping keeps the twist/flip eigenvalues mu +- s sigma_k of the
Hessian non-negative (Smith et al. 2018, Sec. 4) but makes it inexact where it acts, which turns Newton's
quadratic convergence linear. The Newton loop (newton.py) takes the exact Hessian where it is positive
definite, else the clamped one, and ``geometric = 0`` (the Gauss-Newton Hessian) as the last fall-back.

Inversion barrier (IPC-style, Li et al. 2020, on det F instead of a distance). The volumetric term holds J at
one point per tet only; under a sharp tip the discrete minimum of E_el itself can fold a P2 element at its
corners (det F < 0 at some of the 4 check points of order 2, where the line search tests inversion), and
then no load step, however small, converges. Added to E_el at the same 4 points:

    E_b(u) = sum_tets int kappa b(J) dV,   b(J) = -(J - J_hat)^2 ln(J / J_hat)  for 0 < J < J_hat,  0 above,
    kappa = barrier_stiffness * mu (MPa), b -> +inf as J -> 0,

C2 at J_hat, so it changes nothing where every J >= J_hat (the usual case) and makes an inverted element
unreachable from an uninverted state. Gradient kappa b'(J) cof(F) : grad v; Hessian
kappa [b''(J) (cof F : grad du)(cof F : grad v) + geometric b'(J) dcof(F)[grad du] : grad v], with b'' >= 0.

The clamped Hessian is positive semi-definite tet by tet. With A the gradient of du, the deviatoric term gives
mu int |A|^2 = mu sum_q w_q |A_q|^2 over the barrier's 4 check points (order 2 is exact for P2's quadratic |A|^2),
which also bounds mu V |A_c|^2 at the volumetric term's one point (A is linear: A_c is its mean). A geometric term
s dcof(F)[A] : A is at least -|s| sigma_max |A|^2. So each of the two clamped terms alone is covered by the
deviatoric one, and together they are where each gets half: in a tet where the barrier acts at any check point
(``barrier_tets``), the volumetric pressure is clamped to mu/(2 sigma_max), and kappa b'(J) always is. With both at
mu/sigma_max the clamped Hessian had negative eigenvalues in compressed tets where the barrier acts
(tests/test_physics_barrier.py), which is where the device CG found it not positive definite (newton.py).
"""

from __future__ import annotations

import warp as wp
import warp.fem as fem

_f = wp.float64

#: How a Hessian takes the volumetric term's geometric part (the ``clamp`` argument of ``barrier_state_form`` and of
#: volumetric_hessian.py; newton.py ``_hessian_ladder``): as it is, or with the pressure clamped (and the barrier's too).
EXACT = 0
CLAMPED = 1


@wp.func
def _col(F: wp.mat33d, j: int):
    return wp.vec3d(F[0, j], F[1, j], F[2, j])


@wp.func
def cofactor(F: wp.mat33d):
    f0 = _col(F, 0)
    f1 = _col(F, 1)
    f2 = _col(F, 2)
    return wp.matrix_from_cols(wp.cross(f1, f2), wp.cross(f2, f0), wp.cross(f0, f1))


@wp.func
def cofactor_delta(F: wp.mat33d, A: wp.mat33d):
    """Directional derivative of cof(F) along A."""
    f0 = _col(F, 0)
    f1 = _col(F, 1)
    f2 = _col(F, 2)
    a0 = _col(A, 0)
    a1 = _col(A, 1)
    a2 = _col(A, 2)
    return wp.matrix_from_cols(
        wp.cross(a1, f2) + wp.cross(f1, a2),
        wp.cross(a2, f0) + wp.cross(f2, a0),
        wp.cross(a0, f1) + wp.cross(f0, a1),
    )


@wp.func
def pressure_bound(F: wp.mat33d, mu: wp.float64):
    """mu / sigma_max(F): the largest |s| for which the twist/flip eigenvalues mu +- s sigma_k stay >= 0."""
    U = wp.mat33d()
    sig = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(F, U, sig, V)
    return mu / wp.max(wp.max(wp.abs(sig[0]), wp.abs(sig[1])), wp.max(wp.abs(sig[2]), _f(1.0e-6)))


@wp.func
def deformation_gradient(grad_u: wp.mat33d):
    return wp.identity(n=3, dtype=wp.float64) + grad_u


@fem.integrand
def volumetric_energy_form(s: fem.Sample, u: fem.Field, params: wp.array(dtype=wp.vec2d)):
    F = deformation_gradient(fem.grad(u, s))
    mu = params[s.element_index][0]
    lam = params[s.element_index][1]
    c = wp.determinant(F) - _f(1.0) - mu / lam
    return _f(0.5) * lam * c * c


@fem.integrand
def deviatoric_gradient_form(s: fem.Sample, u: fem.Field, v: fem.Field, params: wp.array(dtype=wp.vec2d)):
    F = deformation_gradient(fem.grad(u, s))
    return params[s.element_index][0] * wp.ddot(F, fem.grad(v, s))


@fem.integrand
def volumetric_gradient_form(s: fem.Sample, u: fem.Field, v: fem.Field, params: wp.array(dtype=wp.vec2d)):
    F = deformation_gradient(fem.grad(u, s))
    mu = params[s.element_index][0]
    lam = params[s.element_index][1]
    p = lam * (wp.determinant(F) - _f(1.0) - mu / lam)
    return p * wp.ddot(cofactor(F), fem.grad(v, s))


@fem.integrand
def deviatoric_hessian_form(s: fem.Sample, du: fem.Field, v: fem.Field, params: wp.array(dtype=wp.vec2d)):
    return params[s.element_index][0] * wp.ddot(fem.grad(du, s), fem.grad(v, s))


@fem.integrand
def det_form(s: fem.Sample, u: fem.Field):
    return wp.determinant(deformation_gradient(fem.grad(u, s)))


@wp.func
def det_barrier(J: wp.float64, j_hat: wp.float64):
    """(b, b', b'') of the inversion barrier b(J) = -(J - j_hat)^2 ln(J / j_hat) (0 for J >= j_hat)."""
    if J >= j_hat:
        return wp.vec3d(_f(0.0), _f(0.0), _f(0.0))
    d = J - j_hat
    ln = wp.log(J / j_hat)
    return wp.vec3d(-d * d * ln, -(_f(2.0) * d * ln + d * d / J), -(_f(2.0) * ln + _f(4.0) * d / J - d * d / (J * J)))


@fem.integrand
def barrier_energy_form(s: fem.Sample, u: fem.Field, params: wp.array(dtype=wp.vec2d), stiffness: wp.float64,
                        j_hat: wp.float64):
    J = wp.determinant(deformation_gradient(fem.grad(u, s)))
    return stiffness * params[s.element_index][0] * det_barrier(J, j_hat)[0]


@fem.integrand
def barrier_state_form(s: fem.Sample, u: fem.Field, params: wp.array(dtype=wp.vec2d), stiffness: wp.float64,
                       j_hat: wp.float64, geometric: wp.float64, clamp: int, F_qp: wp.array(dtype=wp.mat33d),
                       b_qp: wp.array(dtype=wp.vec2d), barrier_tets: wp.array(dtype=wp.int32)):
    """Stores F and kappa (geometric b', b'') at each check point for the Hessian (barrier_terms.py), and marks the
    tets where the barrier acts in ``barrier_tets`` (zeroed by the caller); with ``clamp`` kappa b' is clamped to
    mu/(2 sigma_max) (see the module's docstring)."""
    F = deformation_gradient(fem.grad(u, s))
    J = wp.determinant(F)
    b = det_barrier(J, j_hat)
    mu = params[s.element_index][0]
    kappa = stiffness * mu
    p = kappa * b[1]
    if J < j_hat:
        barrier_tets[s.element_index] = 1
    if clamp != 0:
        bound = _f(0.5) * pressure_bound(F, mu)
        p = wp.clamp(p, -bound, bound)
    F_qp[s.qp_index] = F
    b_qp[s.qp_index] = wp.vec2d(geometric * p, kappa * b[2])
