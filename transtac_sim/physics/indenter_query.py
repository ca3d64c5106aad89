"""Where a point of the gel lies against a rigid triangle-mesh indenter: inside or outside, how deep, and which way out
(``penetration``), for the contact's energy and forces (contact.py).

Rigid indenter i: a watertight mesh in its local frame and a pose T_i (4x4, local -> gel frame, mm). For a point x
(gel frame, mm) let q = T_i^-1 x. If q is inside the mesh, the penetration is g = |c - q| with c the closest surface
point, and n = T_i (c - q)/g, the direction that takes x out of the indenter. Inside a face, and on an edge between
two coplanar faces (a plane cut into triangles), g and n are the (float64) distance to the face plane and its normal:
exact. At any other edge or corner they come from the float64 closest point of the face that Warp's float32 query
returns (where two faces are about equally close, the query may return the one a float32 rounding favours). Warp's
float32 closest point, used at every edge and corner before, was up to 8.6e-8 mm and 0.033 off under a plate's bottom
face cut along its diagonal at depths of 1e-4 to 1e-2 mm (a throwaway check on the points of
tests/test_physics_contact_query.py), enough noise in the contact energy to stall Newton.
"""

from __future__ import annotations

import warp as wp

_f = wp.float64


@wp.struct
class Indenters:
    """The indenters as the kernels see them (solver.py ``_indenter_struct``): their meshes and poses for the query,
    and the contact's parameters (contact.py)."""

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
def transform(T: wp.mat44d, x: wp.vec3d):
    """The point x moved by the rigid transform T (4x4)."""
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
def _ratio(num: wp.float64, den: wp.float64):
    """num / den, 0 where den <= 0 (an edge of zero length in a degenerate triangle)."""
    r = _f(0.0)
    if den > _f(0.0):
        r = num / den
    return r


@wp.func
def _closest_on_triangle(p: wp.vec3d, a: wp.vec3d, b: wp.vec3d, c: wp.vec3d):
    """The point of triangle abc closest to p, in float64 (Ericson, Real-Time Collision Detection, 5.1.5; a degenerate
    triangle gives a point of it, not NaN)."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = wp.dot(ab, ap)
    d2 = wp.dot(ac, ap)
    if d1 <= _f(0.0) and d2 <= _f(0.0):
        return a
    bp = p - b
    d3 = wp.dot(ab, bp)
    d4 = wp.dot(ac, bp)
    if d3 >= _f(0.0) and d4 <= d3:
        return b
    vc = d1 * d4 - d3 * d2
    if vc <= _f(0.0) and d1 >= _f(0.0) and d3 <= _f(0.0):
        return a + ab * _ratio(d1, d1 - d3)
    cp = p - c
    d5 = wp.dot(ab, cp)
    d6 = wp.dot(ac, cp)
    if d6 >= _f(0.0) and d5 <= d6:
        return c
    vb = d5 * d2 - d1 * d6
    if vb <= _f(0.0) and d2 >= _f(0.0) and d6 <= _f(0.0):
        return a + ac * _ratio(d2, d2 - d6)
    va = d3 * d6 - d5 * d4
    if va <= _f(0.0) and d4 - d3 >= _f(0.0) and d5 - d6 >= _f(0.0):
        return b + (c - b) * _ratio(d4 - d3, (d4 - d3) + (d5 - d6))
    total = va + vb + vc
    return a + ab * _ratio(vb, total) + ac * _ratio(vc, total)


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
def _on_flat_edge(ind: Indenters, i: int, hit: wp.MeshQueryPoint, nf: wp.vec3d, tol: wp.float32):
    """Whether the closest point of ``hit`` lies on one edge of its face (one barycentric weight <= ``tol``, as in
    ``_feature_side``; not near a corner) whose pseudo-normal is the face's own normal: the edge between two coplanar
    faces of a flat region (a plane cut into triangles; every edge of a closed mesh has two faces), where the face's
    plane gives the depth exactly. Near a corner the answer is no: a corner's pseudo-normal can equal the face's
    normal where its other faces tilt symmetrically, so the float64 closest point is taken there."""
    w = wp.vec3(hit.u, hit.v, wp.float32(1.0) - hit.u - hit.v)
    base = ind.normals_start[i] + 7 * hit.face
    small = 0
    edge = 0
    for k in range(3):
        if w[k] <= tol:
            small += 1
            edge = k
    return small == 1 and wp.dot(ind.normals[base + 4 + edge], nf) >= _f(1.0 - 1.0e-9)


@wp.func
def penetration(ind: Indenters, i: int, x: wp.vec3d):
    """(g, n): penetration depth (mm, 0 if outside) and push-out direction in the gel frame.

    Inside a face (the usual case), and on an edge between two coplanar faces (``_on_flat_edge``), g is the
    distance to the face plane along its outward normal, computed in float64; near any other edge or vertex of the
    indenter n points to the float64 closest point of the face (``_closest_on_triangle``). A point outside
    the mesh's bounding box is outside the mesh: (0, +z) without a mesh query. Inside or outside: where the closest
    point lies inside a face, the side of that face's plane (exact for a closed mesh); at an edge or a vertex, the side
    of that feature's angle-weighted pseudo-normal (``_feature_side``, exact for a closed mesh), checked against
    every feature that the closest point's float32 barycentric weights cannot rule out, and where those disagree the
    winding number (which looks at the whole mesh, so it is the expensive query: the contact kernels took 545 against
    185 us on press_slide on an H100 with the winding number at every edge and vertex and none, BENCHMARKS.md
    ``fem_contact_query_gpu``). Warp's pseudo-normal sign (``mesh_query_point_sign_normal``) was tried and, in a
    review's denser sampling, put a few points deep inside the coin and the pocket block outside: it adds the normals
    of every face within a tolerance of the closest distance instead of taking the closest feature's."""
    q = transform(ind.pose_inv[i], x)
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
    if _inside_face(hit, edge_tol) or _on_flat_edge(ind, i, hit, nf, edge_tol):
        g = wp.dot(p0 - q, nf)
        n = _rotate(ind.pose[i], nf)
    else:
        d = _closest_on_triangle(q, p0, _point(ind.mesh[i], hit.face, 1), _point(ind.mesh[i], hit.face, 2)) - q
        g = wp.length(d)
        if g > _f(1.0e-9):
            n = _rotate(ind.pose[i], d / g)
        else:
            n = _rotate(ind.pose[i], nf)
    g = wp.max(g, _f(0.0))
    return g, n
