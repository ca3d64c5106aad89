"""Penalty contact and lagged smoothed Coulomb friction against rigid triangle-mesh indenters.

Rigid indenter i: a watertight mesh in its local frame and a pose T_i (4x4, local -> gel frame, mm).
At a boundary point of the gel with current position x = X + u(X):

- Normal contact. The penetration g and push-out normal n of x against indenter i (indenter_query.py
  ``penetration``). Energy k/2 g^2 per unit area, so the gel feels the traction k g n (MPa). ``k`` (N/mm^3) is the
  penalty stiffness; at equilibrium the penetration is p/k for a contact pressure p, which the solver checks against a
  stated tolerance.
- Friction (Coulomb, coefficient mu_f), on the slip since the previous (sub)step plus the sticking stretch s carried
  from it, with the normal pressure lam = k g and the normal n lagged at displacement u_lag (IPC-style):
      dx  = x - T_i T_i,prev^-1 (x_prev - s)   (motion of the gel point relative to the indenter)
      u_t = (I - n n^T) dx,  y = |u_t|
      E_f = mu_f lam f0(y),  f0(y) = -y^3/(3 eps^2) + y^2/eps + eps/3 (y < eps), y otherwise,
  whose derivative f1 = f0' = -y^2/eps^2 + 2y/eps (y < eps), 1 otherwise, gives the traction
  -mu_f lam f1(y) u_t/y: sticking springs below a slip of ``eps`` (mm), the Coulomb bound above.
  Its Hessian (exact for the lagged lam and n, positive semi-definite since f1' >= 0 and f1/y >= 0) is
      mu_f lam [ f1(y)/y (I - n n^T) + (f1'(y) - f1(y)/y) t t^T ],   t = u_t / y.
  At a converged step s becomes u_t, shortened to eps where it slipped (y > eps; f1(eps) = 1) and 0 out of contact
  (``stick_form``): the next step starts with the traction this one ended with. Without s (IPC's incremental form,
  made for small time steps) every quasi-static frame started from no friction, so a sticking point crept up to
  eps per frame and a held contact relaxed (``SolverSettings.friction_memory``). The stretch is the smoothing's
  elastic stick, not an exact Coulomb law: a point kept at eps that reverses its slip starts with no stiffness along
  the slip (f1'(eps) = 0) and sheds its traction as the stretch shrinks.

All quantities are integrated over the boundary faces of the gel with a Gauss rule. The lagged quantities and
the current traction and stiffnesses are stored per quadrature point (``ContactState``) before assembly.
"""

from __future__ import annotations

import warp as wp
import warp.fem as fem

from transtac_sim.physics.indenter_query import Indenters, penetration, transform

_f = wp.float64


@wp.func
def _f0(y: wp.float64, eps: wp.float64):
    if y < eps:
        return -y * y * y / (_f(3.0) * eps * eps) + y * y / eps + eps / _f(3.0)
    return y


@wp.func
def _f1_over_y(y: wp.float64, eps: wp.float64):
    if y < eps:
        return -y / (eps * eps) + _f(2.0) / eps
    return _f(1.0) / y


@wp.func
def _df1(y: wp.float64, eps: wp.float64):
    if y < eps:
        return _f(2.0) / eps - _f(2.0) * y / (eps * eps)
    return _f(0.0)


@wp.struct
class ContactState:
    """Per contact quadrature point q and indenter i (index q * count + i), so that the assembly of the
    gradient and Hessian (one integrand call per degree of freedom, or pair of them) makes no mesh query."""

    lag_g: wp.array(dtype=wp.float64)  # penetration at the friction lag u_lag (mm)
    lag_n: wp.array(dtype=wp.vec3d)  # push-out normal at the lag
    normal: wp.array(dtype=wp.vec3d)  # current push-out normal
    k_normal: wp.array(dtype=wp.float64)  # k where in contact, else 0 (N/mm^3)
    k_slip: wp.array(dtype=wp.float64)  # friction's tangential stiffness mu_f k g_lag f1(y)/y (N/mm^3)
    k_slip_dir: wp.array(dtype=wp.float64)  # its correction along the slip: mu_f k g_lag (f1' - f1/y)
    slip_dir: wp.array(dtype=wp.vec3d)  # unit slip direction t
    traction: wp.array(dtype=wp.vec3d)  # total traction on the gel (MPa), index q
    stick: wp.array(dtype=wp.vec3d)  # friction's stretch carried into this step (mm, gel frame at the step's start)
    stick_next: wp.array(dtype=wp.vec3d)  # the same at the end of the last converged step (``stick_form``)


@wp.func
def stiff_at(k_normal: wp.array(dtype=wp.float64), k_slip: wp.array(dtype=wp.float64),
             k_slip_dir: wp.array(dtype=wp.float64), count: int, q: int):
    """Whether any of ``count`` indenters has a normal or friction stiffness at contact quadrature point q (the
    ``ContactState`` entries q * count + i)."""
    for i in range(count):
        j = q * count + i
        if k_normal[j] != wp.float64(0.0) or k_slip[j] != wp.float64(0.0) or k_slip_dir[j] != wp.float64(0.0):
            return True
    return False


@wp.func
def tangential_slip(ind: Indenters, st: ContactState, i: int, j: int, x: wp.vec3d, x_prev: wp.vec3d, n: wp.vec3d):
    """u_t: the slip since the anchor x_prev - stick (carried along with indenter i), in the plane normal to n."""
    dx = x - transform(ind.relative[i], x_prev - st.stick[j])
    return dx - wp.dot(dx, n) * n


@wp.func
def traction(ind: Indenters, st: ContactState, i: int, j: int, x: wp.vec3d, x_prev: wp.vec3d):
    """Traction (MPa) that indenter i applies to the gel at a boundary point (j = q * count + i); also the
    current normal, normal stiffness, friction stiffness, its correction along the slip and the slip
    direction there."""
    g, n = penetration(ind, i, x)
    t = ind.stiffness * g * n
    k_n = _f(0.0)
    if g > _f(0.0):
        k_n = ind.stiffness
    k_t = _f(0.0)
    k_d = _f(0.0)
    t_dir = wp.vec3d(_f(0.0), _f(0.0), _f(0.0))
    gl = st.lag_g[j]
    if gl > _f(0.0) and ind.friction[i] > _f(0.0):
        ut = tangential_slip(ind, st, i, j, x, x_prev, st.lag_n[j])
        y = wp.length(ut)
        c = ind.friction[i] * ind.stiffness * gl
        k_t = c * _f1_over_y(y, ind.slip_eps)
        t -= k_t * ut
        if y > _f(1.0e-12):
            k_d = c * _df1(y, ind.slip_eps) - k_t
            t_dir = ut / y
    return t, n, k_n, k_t, k_d, t_dir


@fem.integrand
def lag_form(s: fem.Sample, domain: fem.Domain, u_lag: fem.Field, ind: Indenters, st: ContactState):
    """Stores the lagged penetration and normal (friction's normal pressure and tangent plane)."""
    x = fem.position(domain, s) + u_lag(s)
    for i in range(ind.count):
        g, n = penetration(ind, i, x)
        st.lag_g[s.qp_index * ind.count + i] = g
        st.lag_n[s.qp_index * ind.count + i] = n


@fem.integrand
def stick_form(s: fem.Sample, domain: fem.Domain, u: fem.Field, u_prev: fem.Field, ind: Indenters, st: ContactState):
    """Stores the stretch of friction's sticking spring at a converged u for the next step: u_t in the tangent plane at
    u where it sticks (y < eps), eps t where it slips, 0 where friction did not act this step (no contact at the last
    lag) or u is out of contact, so that the next step starts with the traction this one ended with. The tangent plane
    is taken at u rather than at the last lag (which can trail u by what the last lag move left), as the next step's
    first lag is unless a warm start moves it."""
    X = fem.position(domain, s)
    for i in range(ind.count):
        j = s.qp_index * ind.count + i
        kept = wp.vec3d(_f(0.0), _f(0.0), _f(0.0))
        g, n = penetration(ind, i, X + u(s))
        if g > _f(0.0) and st.lag_g[j] > _f(0.0) and ind.friction[i] > _f(0.0):
            ut = tangential_slip(ind, st, i, j, X + u(s), X + u_prev(s), n)
            y = wp.length(ut)
            kept = ut
            if y > ind.slip_eps:
                kept = ut * (ind.slip_eps / y)
        st.stick_next[j] = kept


@fem.integrand
def state_form(s: fem.Sample, domain: fem.Domain, u: fem.Field, u_prev: fem.Field, ind: Indenters, st: ContactState):
    """Stores traction and stiffnesses at the current displacement u."""
    X = fem.position(domain, s)
    t_sum = wp.vec3d(_f(0.0), _f(0.0), _f(0.0))
    for i in range(ind.count):
        j = s.qp_index * ind.count + i
        t, n, k_n, k_t, k_d, t_dir = traction(ind, st, i, j, X + u(s), X + u_prev(s))
        t_sum += t
        st.normal[j] = n
        st.k_normal[j] = k_n
        st.k_slip[j] = k_t
        st.k_slip_dir[j] = k_d
        st.slip_dir[j] = t_dir
    st.traction[s.qp_index] = t_sum


@fem.integrand
def contact_energy_form(
    s: fem.Sample, domain: fem.Domain, u: fem.Field, u_prev: fem.Field, ind: Indenters, st: ContactState
):
    X = fem.position(domain, s)
    x = X + u(s)
    e = _f(0.0)
    for i in range(ind.count):
        g, n = penetration(ind, i, x)
        e += _f(0.5) * ind.stiffness * g * g
        j = s.qp_index * ind.count + i
        gl = st.lag_g[j]
        if gl > _f(0.0) and ind.friction[i] > _f(0.0):
            ut = tangential_slip(ind, st, i, j, x, X + u_prev(s), st.lag_n[j])
            e += ind.friction[i] * ind.stiffness * gl * _f0(wp.length(ut), ind.slip_eps)
    return e


@fem.integrand
def contact_gradient_form(s: fem.Sample, v: fem.Field, st: ContactState):
    return -wp.dot(st.traction[s.qp_index], v(s))


@fem.integrand
def contact_hessian_form(s: fem.Sample, du: fem.Field, v: fem.Field, ind: Indenters, st: ContactState,
                         qp_base: wp.array(dtype=int), points: int):
    """On a subset of the contact sides (contact_sides.py): its point s.qp_index is the full quadrature's point
    qp_base[s.qp_index / points] + s.qp_index % points, where the contact state is stored."""
    h = _f(0.0)
    q = qp_base[s.qp_index // points] + s.qp_index % points
    for i in range(ind.count):
        j = q * ind.count + i
        n = st.normal[j]
        h += st.k_normal[j] * wp.dot(n, du(s)) * wp.dot(n, v(s))
        nl = st.lag_n[j]
        dut = du(s) - wp.dot(du(s), nl) * nl
        h += st.k_slip[j] * wp.dot(dut, v(s))
        h += st.k_slip_dir[j] * wp.dot(st.slip_dir[j], du(s)) * wp.dot(st.slip_dir[j], v(s))
    return h


@fem.integrand
def wrench_form(
    s: fem.Sample,
    domain: fem.Domain,
    u: fem.Field,
    u_prev: fem.Field,
    ind: Indenters,
    st: ContactState,
    which: int,
    component: int,
):
    """Component 0-2: force, 3-5: torque about the indenter's reference point (pose translation)."""
    X = fem.position(domain, s)
    x = X + u(s)
    t, n, k_n, k_t, k_d, t_dir = traction(ind, st, which, s.qp_index * ind.count + which, x, X + u_prev(s))
    if component < 3:
        return t[component]
    P = ind.pose[which]
    r = x - wp.vec3d(P[0, 3], P[1, 3], P[2, 3])
    return wp.cross(r, t)[component - 3]


@fem.integrand
def penetration_form(s: fem.Sample, domain: fem.Domain, u: fem.Field, ind: Indenters):
    x = fem.position(domain, s) + u(s)
    g_max = _f(0.0)
    for i in range(ind.count):
        g, n = penetration(ind, i, x)
        g_max = wp.max(g_max, g)
    return g_max
