"""Penalty contact and lagged smoothed Coulomb friction against rigid triangle-mesh indenters.

Rigid indenter i: a watertight mesh in its local frame and a pose T_i (4x4, local -> gel frame, mm).
At a boundary point of the gel with current position x = X + u(X):

- Normal contact. Let q = T_i^-1 x. If q is inside the mesh (the side of the closest face's plane, or at an edge or a
  vertex the winding number; ``penetration``), the penetration is
  g = |c - q| with c the closest surface point, and n = T_i (c - q)/g (the direction that takes x out of
  the indenter). Inside a face, g and n are the (float64) distance to the face plane and its normal,
  which stays accurate for tiny penetrations where the float32 closest point would not. Energy k/2 g^2 per unit area, so the gel feels the traction
  k g n (MPa). ``k`` (N/mm^3) is the penalty stiffness; at equilibrium the penetration is p/k for a contact
  pressure p, which the solver checks against a stated tolerance.
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
  eps per frame and a held contact relaxed (``SolverSettings.friction_memory``).

All quantities are integrated over the boundary faces of the gel with a Gauss rule. The lagged quantities and
the current traction and stiffnesses are stored per quadrature point (``ContactState``) before assembly.
"""

from __future__ import annotations

import warp as wp
import warp.fem as fem

_f = wp.float64


@wp.struct
class Indenters:
    mesh: wp.array(dtype=wp.uint64)
    pose: wp.array(dtype=wp.mat44d)  # local -> gel, current
    pose_inv: wp.array(dtype=wp.mat44d)  # gel -> local, current
    relative: wp.array(dtype=wp.mat44d)  # T_cur T_prev^-1: where a point stuck to the indenter moved
    max_dist: wp.array(dtype=wp.float64)  # bounding radius of each mesh (mm)
    box_lo: wp.array(dtype=wp.vec3d)  # each mesh's bounding box in its local frame (mm): no query outside it
    box_hi: wp.array(dtype=wp.vec3d)
    normals: wp.array(dtype=wp.vec3d)  # every mesh's ``RigidIndenter.feature_normals``, 7 per face, one after another
    normals_start: wp.array(dtype=int)  # where each mesh's normals start in ``normals``
    friction: wp.array(dtype=wp.float64)
    count: int
    stiffness: wp.float64  # penalty k (N/mm^3)
    slip_eps: wp.float64  # friction smoothing (mm)


@wp.func
def _transform(T: wp.mat44d, x: wp.vec3d):
    return wp.vec3d(
        T[0, 0] * x[0] + T[0, 1] * x[1] + T[0, 2] * x[2] + T[0, 3],
        T[1, 0] * x[0] + T[1, 1] * x[1] + T[1, 2] * x[2] + T[1, 3],
        T[2, 0] * x[0] + T[2, 1] * x[1] + T[2, 2] * x[2] + T[2, 3],
    )


@wp.func
def _rotate(T: wp.mat44d, x: wp.vec3d):
    return wp.vec3d(
        T[0, 0] * x[0] + T[0, 1] * x[1] + T[0, 2] * x[2],
        T[1, 0] * x[0] + T[1, 1] * x[1] + T[1, 2] * x[2],
        T[2, 0] * x[0] + T[2, 1] * x[1] + T[2, 2] * x[2],
    )


@wp.func
def _point(mesh: wp.uint64, face: int, k: int):
    m = wp.mesh_get(mesh)
    p = m.points[m.indices[3 * face + k]]
    return wp.vec3d(_f(p[0]), _f(p[1]), _f(p[2]))


@wp.func
def _face_plane(mesh: wp.uint64, face: int):
    """(a vertex, the unit outward normal) of a mesh face, in float64."""
    p0 = _point(mesh, face, 0)
    return p0, wp.normalize(wp.cross(_point(mesh, face, 1) - p0, _point(mesh, face, 2) - p0))


@wp.func
def _inside_face(hit: wp.MeshQueryPoint, tol: wp.float32):
    """Whether the closest point of ``hit`` lies inside its face, away from the face's edges by ``tol`` (barycentric)."""
    return hit.u > tol and hit.v > tol and wp.float32(1.0) - hit.u - hit.v > tol


@wp.func
def _feature_side(ind: Indenters, i: int, hit: wp.MeshQueryPoint, q: wp.vec3d, tol: wp.float32):
    """Which side of indenter i's mesh q (local frame) lies on, from its closest point c on face ``hit.face`` near
    the face's boundary (a barycentric weight <= ``tol``): +1 outside, -1 inside, 0 undecided. c lies on the face, on
    an edge (its opposite weight about 0) or at a vertex (the other two about 0), and each of these features consistent
    with the weights gives a side, (q - c) . (its pseudo-normal) (``RigidIndenter.feature_normals``), exact for the
    feature that holds c (Baerentzen & Aanaes 2005); decided where all of them agree, else 0."""
    w = wp.vec3(hit.u, hit.v, wp.float32(1.0) - hit.u - hit.v)
    c = _f(w[0]) * _point(ind.mesh[i], hit.face, 0) + _f(w[1]) * _point(ind.mesh[i], hit.face, 1) \
        + _f(w[2]) * _point(ind.mesh[i], hit.face, 2)
    d = q - c
    base = ind.normals_start[i] + 7 * hit.face
    lowest = wp.dot(d, ind.normals[base])  # the face
    highest = lowest
    for k in range(3):
        if w[k] <= tol:  # the edge opposite corner k
            s = wp.dot(d, ind.normals[base + 4 + k])
            lowest = wp.min(lowest, s)
            highest = wp.max(highest, s)
        if w[(k + 1) % 3] <= tol and w[(k + 2) % 3] <= tol:  # corner k
            s = wp.dot(d, ind.normals[base + 1 + k])
            lowest = wp.min(lowest, s)
            highest = wp.max(highest, s)
    side = 0
    if lowest > _f(0.0):
        side = 1
    elif highest < _f(0.0):
        side = -1
    return side


@wp.func
def penetration(ind: Indenters, i: int, x: wp.vec3d):
    """(g, n): penetration depth (mm, 0 if outside) and push-out direction in the gel frame.

    Inside a face (the usual case) g is the distance to the face plane along its outward normal,
    computed in float64; near an edge or a vertex of the indenter n points to the closest point. A point outside
    the mesh's bounding box is outside the mesh: (0, +z) without a mesh query. Inside or outside: where the closest
    point lies inside a face, the side of that face's plane (exact for a closed mesh); at an edge or a vertex, the side
    of that feature's angle-weighted pseudo-normal (``_feature_side``, exact for a closed mesh), checked against
    every feature that the closest point's float32 barycentric weights cannot rule out, and where those disagree the
    winding number (which looks at the whole mesh, so it is the expensive query: the contact kernels took 545 against
    185 us on press_slide on an H100 with the winding number at every edge and vertex and none, BENCHMARKS.md
    ``fem_contact_query_gpu``). Warp's pseudo-normal sign (``mesh_query_point_sign_normal``) was tried and, in a
    review's denser sampling, put a few points deep inside the coin and the pocket block outside: it adds the normals
    of every face within a tolerance of the closest distance instead of taking the closest feature's."""
    q = _transform(ind.pose_inv[i], x)
    g = _f(0.0)
    n = wp.vec3d(_f(0.0), _f(0.0), _f(1.0))
    lo = ind.box_lo[i]
    hi = ind.box_hi[i]
    if q[0] < lo[0] or q[1] < lo[1] or q[2] < lo[2] or q[0] > hi[0] or q[1] > hi[1] or q[2] > hi[2]:
        return g, n
    qf = wp.vec3(wp.float32(q[0]), wp.float32(q[1]), wp.float32(q[2]))
    edge_tol = wp.float32(1.0e-4)
    hit = wp.mesh_query_point_no_sign(ind.mesh[i], qf, wp.float32(ind.max_dist[i]))
    if not hit.result:
        return g, n
    p0, nf = _face_plane(ind.mesh[i], hit.face)
    if _inside_face(hit, edge_tol):
        g = wp.dot(p0 - q, nf)
        if g > _f(0.0):
            n = _rotate(ind.pose[i], nf)
        else:
            g = _f(0.0)
        return g, n
    side = _feature_side(ind, i, hit, q, edge_tol)
    if side > 0:
        return g, n
    if side == 0:  # undecided: the winding number, with its own closest point
        hit = wp.mesh_query_point_sign_winding_number(ind.mesh[i], qf, wp.float32(ind.max_dist[i]))
        if not (hit.result and hit.sign < 0.0):
            return g, n
        p0, nf = _face_plane(ind.mesh[i], hit.face)
    if _inside_face(hit, edge_tol):
        g = wp.dot(p0 - q, nf)
        n = _rotate(ind.pose[i], nf)
    else:
        cf = wp.mesh_eval_position(ind.mesh[i], hit.face, hit.u, hit.v)
        d = wp.vec3d(_f(cf[0]), _f(cf[1]), _f(cf[2])) - q
        g = wp.length(d)
        if g > _f(1.0e-9):
            n = _rotate(ind.pose[i], d / g)
        else:
            n = _rotate(ind.pose[i], nf)
    g = wp.max(g, _f(0.0))
    return g, n


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
def tangential_slip(ind: Indenters, st: ContactState, i: int, j: int, x: wp.vec3d, x_prev: wp.vec3d):
    """u_t: the slip since the anchor x_prev - stick (carried along with indenter i), in the lagged tangent plane."""
    dx = x - _transform(ind.relative[i], x_prev - st.stick[j])
    n = st.lag_n[j]
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
        ut = tangential_slip(ind, st, i, j, x, x_prev)
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
    """Stores the stretch of friction's sticking spring at a converged u for the next step: u_t where it sticks
    (y < eps), eps t where it slips, 0 out of contact, so that the next step starts with the traction this one ended
    with."""
    X = fem.position(domain, s)
    for i in range(ind.count):
        j = s.qp_index * ind.count + i
        kept = wp.vec3d(_f(0.0), _f(0.0), _f(0.0))
        if st.lag_g[j] > _f(0.0) and ind.friction[i] > _f(0.0):
            ut = tangential_slip(ind, st, i, j, X + u(s), X + u_prev(s))
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
            ut = tangential_slip(ind, st, i, j, x, X + u_prev(s))
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
