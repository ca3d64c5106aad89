"""Stable Neo-Hookean elasticity forms for ``warp.fem`` (float64), per-tet material.

Energy of the gel, with u the displacement (mm), F = I + grad u, params (mu, lam) per tet (MPa):

    E_el(u) = sum_tets  int mu/2 (|F|^2 - 3) dV  +  int lam/2 (J - alpha)^2 dV,   alpha = 1 + mu/lam

The deviatoric-like term is integrated exactly (order 2 for P2); the volumetric term is integrated with
one point per tet (selective reduced integration). For P2 tets this is the displacement-based form of
the P2-P0 mixed element: the incompressibility constraint is imposed once per tet, so nu -> 0.5 does
not lock, while the fully integrated mu-term keeps the stiffness matrix free of spurious modes.

Gradient (N):   mu F : grad v  +  s cof(F) : grad v,          s = lam (J - alpha)
Hessian:        mu grad du : grad v + lam (cof F : grad du)(cof F : grad v) + s_h dcof(F)[grad du] : grad v

with cof(F) = dJ/dF = [f1 x f2, f2 x f0, f0 x f1] (columns f_i of F). ``s_h`` is ``geometric`` times
either ``s`` itself (the exact Hessian) or, with ``clamp``, ``s`` clamped to [-mu/sigma_max, mu/sigma_max]
(sigma_max the largest singular value of F); clamping keeps the twist/flip eigenvalues mu +- s sigma_k of the
Hessian non-negative (Smith et al. 2018, Sec. 4) but makes it inexact where it acts, which turns Newton's
quadratic convergence linear. The Newton loop (newton.py) takes the exact Hessian where it is positive
definite, else the clamped one, and ``geometric = 0`` (the Gauss-Newton Hessian) as the last fall-back.
"""

from __future__ import annotations

import warp as wp
import warp.fem as fem

_f = wp.float64


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
def deformation_gradient(grad_u: wp.mat33d):
    return wp.identity(n=3, dtype=wp.float64) + grad_u


@fem.integrand
def deviatoric_energy_form(s: fem.Sample, u: fem.Field, params: wp.array(dtype=wp.vec2d)):
    F = deformation_gradient(fem.grad(u, s))
    return _f(0.5) * params[s.element_index][0] * (wp.ddot(F, F) - _f(3.0))


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
def volumetric_state_form(
    s: fem.Sample,
    u: fem.Field,
    params: wp.array(dtype=wp.vec2d),
    geometric: wp.float64,
    clamp: int,
    F_qp: wp.array(dtype=wp.mat33d),
    p_qp: wp.array(dtype=wp.float64),
):
    """Stores F and the pressure s_h (clamped if ``clamp``) at each quadrature point, so that the Hessian's
    assembly (which evaluates its integrand once per pair of degrees of freedom) does not repeat the SVD."""
    F = deformation_gradient(fem.grad(u, s))
    mu = params[s.element_index][0]
    lam = params[s.element_index][1]
    p = lam * (wp.determinant(F) - _f(1.0) - mu / lam)
    U = wp.mat33d()
    sig = wp.vec3d()
    V = wp.mat33d()
    wp.svd3(F, U, sig, V)
    bound = mu / wp.max(wp.max(wp.abs(sig[0]), wp.abs(sig[1])), wp.max(wp.abs(sig[2]), _f(1.0e-6)))
    F_qp[s.qp_index] = F
    if clamp != 0:
        p = wp.clamp(p, -bound, bound)
    p_qp[s.qp_index] = geometric * p


@fem.integrand
def volumetric_hessian_form(
    s: fem.Sample,
    du: fem.Field,
    v: fem.Field,
    params: wp.array(dtype=wp.vec2d),
    F_qp: wp.array(dtype=wp.mat33d),
    p_qp: wp.array(dtype=wp.float64),
):
    F = F_qp[s.qp_index]
    cof = cofactor(F)
    gdu = fem.grad(du, s)
    gv = fem.grad(v, s)
    lam = params[s.element_index][1]
    return lam * wp.ddot(cof, gdu) * wp.ddot(cof, gv) + p_qp[s.qp_index] * wp.ddot(cofactor_delta(F, gdu), gv)


@fem.integrand
def det_form(s: fem.Sample, u: fem.Field):
    return wp.determinant(deformation_gradient(fem.grad(u, s)))
