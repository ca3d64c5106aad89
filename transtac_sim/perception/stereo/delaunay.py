"""Prior-guided Delaunay stereo matching (the TransTac paper's matcher), on rectified pixels.

1. Initialisation: the epipolar nearest neighbour nn(i) of every left point (``matching``).
2. Delaunay triangulations of both views (``scipy.spatial.Delaunay`` for the left view; of the right view
   only its triangles that step 4 asks about are needed: a triangle is one of them when its circumcircle
   holds no other right point, checked directly, and the right view is triangulated only where that is
   too close to call, as for points on a common circle).
3. Descriptor of a triangle with ordered vertices (p0, p1, p2): its edge lengths opposite each vertex
   over the perimeter, D = (|p1 p2|, |p2 p0|, |p0 p1|) / perimeter (invariant to translation and scale).
   Two triangles with corresponding vertices are similar when max |D - D'| <= ``desc_tol`` and their
   orientations (sign of the signed area) agree.
4. Anchors: left triangles (a, b, c) whose initial matches (nn(a), nn(b), nn(c)) are distinct and form
   a triangle of the right view's triangulation, similar to (a, b, c), with each pair in the epipolar
   gate and disparities spread by no more than the x tolerance of step 5 (epipolar consistency).
5. Propagation, in rounds over the left triangulation's edges: an unmatched left point c with two
   matched neighbours a, b (the nearest two; when a, b are neighbours of each other too, (a, b, c) is
   the Delaunay triangle next to an accepted one) is predicted in the right view at
   c + (o_a + o_b) / 2, o = right - left the rectified offset of a matched pair (the local disparity and
   the local refraction offset in y vary smoothly). The right point nearest the prediction is accepted
   when it lies within ``prop_tol_px`` (x, y) of it, has a plausible disparity, is not taken, and the
   triangles (a, b, c) and (a', b', c') are similar; a right point proposed twice in a round goes to
   the nearer proposal. The epipolar gate tau_epi is not applied here: the neighbours' offsets predict
   the refraction offset in y, so tau_epi can be tight for the anchors (precise) while propagation still
   finds the pairs offset by more than tau_epi (recall).
6. When a round accepts nothing, the left points it tried (most have no partner: missing in the right
   view, or spurious) leave the triangulation, the rest is triangulated again and step 5 goes on, so a
   missing point does not cut off the region behind it. (Removing points changes the Delaunay
   triangulation only among their neighbours: when none of those is unmatched, step 5 cannot go on and
   the matching ends without triangulating again.)
The result holds the anchored and propagated matches only: initial matches that no consistent triangle
confirms are dropped (that is what keeps precision when a point is missing in one view and the nearest
neighbour is a wrong one). Where a view has no triangulation (fewer than 3 points, or all on a line) the
gated one-to-one assignment (``matching.match_hungarian``) is returned, so that no right point is matched twice.

Every step works on whole arrays (all triangles, all edges, all points of a round at once); the edges of
step 5 come from the triangles once per triangulation, sorted by point and length.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from transtac_sim.perception.stereo.calibration import StereoCalibration
from transtac_sim.perception.stereo.matching import (
    Candidates,
    MatchParams,
    candidates,
    match_hungarian,
    nn_from_candidates,
)

# A triangle's ordered vertex pairs (j, k), j != k, in the order of Delaunay.vertex_neighbor_vertices'
# scan, and the vertex opposite each pair's edge.
_J, _K, _OPPOSITE = np.array([0, 0, 1, 1, 2, 2]), np.array([1, 2, 0, 2, 0, 1]), np.array([2, 1, 2, 0, 1, 0])
_CYCLE = [0, 1, 2, 0, 1]  # a triangle's vertices p0 p1 p2 p0 p1: the edge opposite vertex k is [k + 1] - [k + 2]
_TRUE = np.ones(1, dtype=bool)


def similar(left: np.ndarray, right: np.ndarray, tol: float) -> np.ndarray:
    """Whether triangles left, right (..., 3, 2) with corresponding vertices are similar (module docstring)."""
    p = np.stack(np.broadcast_arrays(left, right))[..., _CYCLE, :]
    return _similar(np.moveaxis(p[..., 0], -1, 1), np.moveaxis(p[..., 1], -1, 1), tol)


def _similar(x: np.ndarray, y: np.ndarray, tol: float) -> np.ndarray:
    """``similar`` of the triangles of view 0 and view 1 with vertex coordinates x, y (2, 5, ...), the
    vertices in ``_CYCLE`` order: both views in one pass, each edge over all triangles at once. A triangle's
    descriptor is its edge lengths (the edge opposite vertex k) over its perimeter; similar triangles have
    descriptors within ``tol`` of each other and signed areas of the same sign (the same orientation)."""
    ex, ey = x[:, 1:4] - x[:, 2:5], y[:, 1:4] - y[:, 2:5]  # p1 - p2, p2 - p0, p0 - p1
    e = np.sqrt(ex * ex + ey * ey)
    desc = e / np.maximum(e[:, 0] + e[:, 1] + e[:, 2], 1e-12)[:, None]
    area = ey[:, 2] * ex[:, 1] - ex[:, 2] * ey[:, 1]  # (p1 - p0) x (p2 - p0)
    return (np.sign(area[0]) == np.sign(area[1])) & (np.abs(desc[0] - desc[1]).max(axis=0) <= tol)


def _triangles(points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The Delaunay triangles (T, 3) of ``points`` and their neighbours (T, 3) (the triangle opposite each
    vertex, -1 on the hull); None when there are none."""
    try:
        t = Delaunay(points)
    except (QhullError, ValueError):
        return None  # fewer than 3 points, or all on one line
    return t.simplices, t.neighbors


def _edges(tri: tuple[np.ndarray, np.ndarray], idx: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The edges (v, w) of a triangulation ``tri`` of ``points[idx]`` in both directions, as indices into
    ``points``, sorted by v, then by length, then in the order of ``Delaunay.vertex_neighbor_vertices``."""
    s, nb = tri
    first = (nb < 0) | (nb > np.arange(len(s))[:, None])  # an inner edge is listed by the first of its triangles
    keep = first[:, _OPPOSITE]
    v, w = idx[s[:, _J][keep]], idx[s[:, _K][keep]]
    dx, dy = points[v, 0] - points[w, 0], points[v, 1] - points[w, 1]
    order = np.lexsort((np.sqrt(dx * dx + dy * dy), v))  # the lengths of np.linalg.norm
    return v[order], w[order]


def _delaunay_triangles(points: np.ndarray, tri: np.ndarray, rel_tol: float = 1e-6) -> np.ndarray | None:
    """Whether each triangle ``tri`` (T, 3) of ``points`` (M, 2) is one of their Delaunay triangulation:
    no point strictly inside its circumcircle (points in general position). None when that is too close
    to call: the nearest other point within ``rel_tol`` r^2 + 1e-6 px^2 of the circle in d^2 - r^2 (d its
    distance from the centre), a triangle flat to ``rel_tol``, non-finite points, or no triangles."""
    if len(tri) == 0 or not np.all(np.isfinite(points)):
        return None
    a = points[tri[:, 0]]
    u, v = points[tri[:, 1]] - a, points[tri[:, 2]] - a
    uu, vv = u[:, 0] ** 2 + u[:, 1] ** 2, v[:, 0] ** 2 + v[:, 1] ** 2
    cross = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    if np.any(np.abs(cross) <= rel_tol * (uu + vv)):
        return None
    o = np.column_stack([v[:, 1] * uu - u[:, 1] * vv, u[:, 0] * vv - v[:, 0] * uu]) / (2 * cross)[:, None]
    r2 = o[:, 0] ** 2 + o[:, 1] ** 2
    o += a  # the circumcentre
    # d^2 - r^2 = |p|^2 - 2 p.o + |o|^2 - r^2 (rounding ~1e-9 px^2 for coordinates ~1000 px, far below the tolerance)
    excess = (-2 * o) @ points.T
    excess += points[:, 0] ** 2 + points[:, 1] ** 2
    excess += (o[:, 0] ** 2 + o[:, 1] ** 2 - r2)[:, None]
    excess[np.arange(len(tri))[:, None], tri] = np.inf  # the triangle's own vertices
    nearest, tol = excess.min(axis=1), rel_tol * r2 + 1e-6
    if np.any(np.abs(nearest) <= tol):
        return None
    return nearest > tol


def anchors(c: Candidates, nn: np.ndarray, tri_left: np.ndarray, points: np.ndarray,
            params: MatchParams) -> np.ndarray | None:
    """Indices of the left triangles (rows of ``tri_left``) that anchor (module docstring, step 4); None
    when the right view has no triangulation. ``points``: the left then the right points."""
    j = nn[tri_left]
    t = np.sort(j, axis=1)
    rows = np.flatnonzero((t[:, 0] >= 0) & (t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]))
    s, j = tri_left[rows], j[rows]
    g, d = c.gate[s, j], c.disparity[s, j]
    spread = np.maximum(np.maximum(d[:, 0], d[:, 1]), d[:, 2]) - np.minimum(np.minimum(d[:, 0], d[:, 1]), d[:, 2])
    ok = g[:, 0] & g[:, 1] & g[:, 2] & (spread <= params.prop_tol_px[0])
    rows, s, j = rows[ok], s[ok], j[ok]
    i = np.stack([s.T[_CYCLE], j.T[_CYCLE] + len(c.left)])  # (2, 5, K) into ``points``
    ok = _similar(points[i, 0], points[i, 1], params.desc_tol)
    rows, j = rows[ok], j[ok]
    # Is (j0, j1, j2) a triangle of the right view's Delaunay triangulation? Its empty circumcircle says so
    # (without triangulating), unless that is too close to call: then the triangulation decides.
    in_right = _delaunay_triangles(c.right, j)
    if in_right is None:
        tri_right = _triangles(c.right)
        if tri_right is None:
            return None
        M = len(c.right)

        def key(t: np.ndarray) -> np.ndarray:  # one integer per vertex set
            t = np.sort(t, axis=1).astype(np.int64)
            return (t[:, 0] * M + t[:, 1]) * M + t[:, 2]

        right_keys = np.sort(key(tri_right[0]))
        k = key(j)
        in_right = right_keys[np.minimum(np.searchsorted(right_keys, k), len(right_keys) - 1)] == k
    return rows[in_right]


def _nearest(points: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Index of the point (M, 2) nearest each query point (K, 2), as ``cKDTree(points).query``: all
    distances at once, the tree only for a query whose two nearest are within rounding of a tie."""
    dx, dy = points[:, 0] - query[:, 0, None], points[:, 1] - query[:, 1, None]
    d2 = dx * dx + dy * dy
    j = np.argmin(d2, axis=1)
    if d2.shape[1] > 1:
        two = np.partition(d2, 1, axis=1)
        tie = two[:, 1] - two[:, 0] <= 1e-9 * two[:, 1]
        if tie.any():
            j[tie] = cKDTree(points).query(query[tie])[1]
    return j


def _grow(c: Candidates, points: np.ndarray, v_all: np.ndarray, w_all: np.ndarray, match: np.ndarray,
          taken: np.ndarray, params: MatchParams) -> np.ndarray:
    """Rounds of step 5 over the edges (``v_all``, ``w_all``) of ``_edges`` until one accepts nothing;
    updates ``match`` and ``taken`` in place and returns the left points tried in that round."""
    tol_x, tol_y = params.prop_tol_px
    N, M = len(c.left), len(c.right)
    while True:
        # each unmatched left point with its two nearest matched neighbours a, b (the edges are sorted)
        matched = match >= 0
        sel = matched[w_all] & ~matched[v_all]
        v, w = v_all[sel], w_all[sel]
        if len(v) < 2:
            return v[:0]
        same = v[1:] == v[:-1]
        first = np.flatnonzero(same & np.concatenate([_TRUE, ~same[:-1]]))
        new, a, b = v[first], w[first], w[first + 1]
        if len(new) == 0:
            return new
        ma, mb = match[a], match[b]
        pred = c.left[new] + ((c.right[ma] - c.left[a]) + (c.right[mb] - c.left[b])) / 2
        j = _nearest(c.right, pred)
        resid = np.abs(c.right[j] - pred)
        ok = (resid[:, 0] <= tol_x) & (resid[:, 1] <= tol_y) & ~taken[j]
        ok &= np.abs(c.disparity[new, j] - c.d_ref) <= params.disparity_halfwidth_px
        k = np.flatnonzero(ok)
        if len(k):
            jn, an, bn = j[k] + N, ma[k] + N, mb[k] + N
            nk, ak, bk = new[k], a[k], b[k]
            i = np.array([[nk, ak, bk, nk, ak], [jn, an, bn, jn, an]])  # (2, 5, K) into ``points``
            k = k[_similar(points[i, 0], points[i, 1], params.desc_tol)]
        if len(k) == 0:
            return new
        if np.bincount(j[k], minlength=M).max() > 1:  # a right point predicted twice: the nearer wins
            k = k[np.argsort(resid[k].sum(axis=1), kind="stable")]
            k = k[np.unique(j[k], return_index=True)[1]]
        jk = j[k]
        match[new[k]] = jk
        taken[jk] = True


def propagate(c: Candidates, tri_left: tuple[np.ndarray, np.ndarray], points: np.ndarray, match: np.ndarray,
              params: MatchParams) -> None:
    """Grow ``match`` (N,) in place (module docstring, steps 5 and 6), starting on the left triangulation
    ``tri_left`` (``_triangles``); ``points``: the left then the right points."""
    taken = np.zeros(len(c.right), dtype=bool)
    taken[match[match >= 0]] = True
    active = np.ones(len(c.left), dtype=bool)
    idx, tri = np.arange(len(c.left)), tri_left
    while tri is not None:
        v, w = _edges(tri, idx, c.left)
        failed = _grow(c, points, v, w, match, taken, params)
        if len(failed) == 0:
            return
        active[failed] = False
        # Removing points changes the triangulation only around them (their neighbours' edges); when none of
        # their neighbours is an unmatched point still in it, no point has new matched neighbours: done.
        is_failed = np.zeros(len(c.left), dtype=bool)
        is_failed[failed] = True
        around = w[is_failed[v]]
        if not np.any(active[around] & (match[around] < 0)):
            return
        idx = np.flatnonzero(active)
        tri = _triangles(c.left[idx])


def match_delaunay(left_uv: np.ndarray, right_uv: np.ndarray, calib: StereoCalibration,
                   params: MatchParams = MatchParams()) -> np.ndarray:
    """Prior-guided Delaunay matching (module docstring): pairs (K, 2) of left and right indices."""
    c = candidates(left_uv, right_uv, calib, params)
    nn = nn_from_candidates(c)
    tri_l = _triangles(c.left)
    points = np.concatenate([c.left, c.right])
    good = None if tri_l is None else anchors(c, nn, tri_l[0], points, params)
    if good is None:  # a view without triangulation: one-to-one, no right point matched twice
        return match_hungarian(left_uv, right_uv, calib, params)
    s = tri_l[0]
    in_good = np.zeros(len(c.left), dtype=bool)
    in_good[s[good].ravel()] = True
    claims = np.bincount(nn[in_good], minlength=len(c.right))
    good = good[~np.any(claims[nn[s[good]]] > 1, axis=1)]  # a right point claimed for two left points
    match = np.full(len(c.left), -1)
    in_good[:] = False
    in_good[s[good].ravel()] = True
    match[in_good] = nn[in_good]
    propagate(c, tri_l, points, match, params)
    i = np.flatnonzero(match >= 0)
    return np.column_stack([i, match[i]]).astype(np.int64)
