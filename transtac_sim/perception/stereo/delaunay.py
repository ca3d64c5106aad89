"""Prior-guided Delaunay stereo matching (the TransTac paper's matcher), on rectified pixels.

1. Initialisation: the epipolar nearest neighbour nn(i) of every left point (``matching``).
2. Delaunay triangulations of both views (``scipy.spatial.Delaunay``).
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
   missing point does not cut off the region behind it.
The result holds the anchored and propagated matches only: initial matches that no consistent triangle
confirms are dropped (that is what keeps precision when a point is missing in one view and the nearest
neighbour is a wrong one). With fewer than 3 points in a view the epipolar NN result is returned.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from transtac_sim.perception.stereo.calibration import StereoCalibration
from transtac_sim.perception.stereo.matching import (
    Candidates,
    MatchParams,
    candidates,
    match_epipolar_nn,
    nn_from_candidates,
)


def descriptor(p: np.ndarray) -> np.ndarray:
    """Normalised edge lengths (..., 3) of triangles p (..., 3, 2): edge opposite vertex k over the perimeter."""
    e = np.linalg.norm(p[..., [1, 2, 0], :] - p[..., [2, 0, 1], :], axis=-1)
    return e / np.maximum(e.sum(axis=-1, keepdims=True), 1e-12)


def signed_area(p: np.ndarray) -> np.ndarray:
    """Twice the signed area of triangles p (..., 3, 2) (px^2)."""
    u, v = p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :]
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def similar(left: np.ndarray, right: np.ndarray, tol: float) -> np.ndarray:
    """Whether triangles left, right (..., 3, 2) with corresponding vertices are similar (module docstring)."""
    same_turn = np.sign(signed_area(left)) == np.sign(signed_area(right))
    return same_turn & (np.abs(descriptor(left) - descriptor(right)).max(axis=-1) <= tol)


def _triangulation(points: np.ndarray) -> Delaunay | None:
    try:
        return Delaunay(points)
    except (QhullError, ValueError):
        return None  # fewer than 3 points, or all on one line


def anchors(c: Candidates, nn: np.ndarray, tri_left: Delaunay, tri_right: Delaunay,
            params: MatchParams) -> np.ndarray:
    """Indices of the left triangles that anchor (module docstring, step 4)."""
    s = tri_left.simplices
    j = nn[s]
    ok = np.all(j >= 0, axis=1) & (j[:, 0] != j[:, 1]) & (j[:, 1] != j[:, 2]) & (j[:, 0] != j[:, 2])
    M = len(c.right)

    def key(t: np.ndarray) -> np.ndarray:  # one integer per vertex set
        t = np.sort(t, axis=1)
        return (t[:, 0] * M + t[:, 1]) * M + t[:, 2]

    ok &= np.isin(key(j), key(tri_right.simplices))
    jj = np.where(j >= 0, j, 0)
    ok &= similar(c.left[s], c.right[jj], params.desc_tol)
    d = c.disparity[s, jj]
    ok &= np.all(c.gate[s, jj], axis=1) & (np.ptp(d, axis=1) <= params.prop_tol_px[0])
    return np.flatnonzero(ok)


def _two_nearest_matched(edges: np.ndarray, match: np.ndarray) -> np.ndarray:
    """Triangles (K, 3) (v, a, b): each unmatched left point v with its two nearest matched neighbours
    a, b along ``edges`` (E, 2) (v, neighbour), sorted by v and then by length."""
    e = edges[(match[edges[:, 0]] < 0) & (match[edges[:, 1]] >= 0)]
    _, start, count = np.unique(e[:, 0], return_index=True, return_counts=True)
    first, second = start[count >= 2], start[count >= 2] + 1
    return np.column_stack([e[first, 0], e[first, 1], e[second, 1]])


def _grow(c: Candidates, edges: np.ndarray, match: np.ndarray, taken: np.ndarray, params: MatchParams) -> np.ndarray:
    """Rounds of step 5 over the graph ``edges`` until one accepts nothing; updates ``match`` and ``taken``
    in place and returns the left points tried in that round."""
    tree, tol = cKDTree(c.right), np.asarray(params.prop_tol_px)
    while True:
        tri = _two_nearest_matched(edges, match)
        new, shared = tri[:, 0], tri[:, 1:]
        pred = c.left[new] + (c.right[match[shared]] - c.left[shared]).mean(axis=1)
        _, j = tree.query(pred)
        j = np.asarray(j, dtype=np.int64).reshape(-1)
        resid = np.abs(c.right[j] - pred)
        ok = np.all(resid <= tol, axis=1) & ~taken[j]
        ok &= np.abs(c.disparity[new, j] - c.d_ref) <= params.disparity_halfwidth_px
        ok &= similar(c.left[tri], c.right[np.column_stack([j, match[shared]])], params.desc_tol)
        order = np.flatnonzero(ok)[np.argsort(resid[ok].sum(axis=1), kind="stable")]
        _, first = np.unique(j[order], return_index=True)  # a right point predicted twice: the nearer wins
        if len(first) == 0:
            return new
        match[new[order[first]]], taken[j[order[first]]] = j[order[first]], True


def propagate(c: Candidates, tri_left: Delaunay, match: np.ndarray, params: MatchParams) -> None:
    """Grow ``match`` (N,) in place (module docstring, steps 5 and 6), starting on ``tri_left``."""
    taken = np.zeros(len(c.right), dtype=bool)
    taken[match[match >= 0]] = True
    active = np.ones(len(c.left), dtype=bool)
    idx, tri = np.arange(len(c.left)), tri_left
    while tri is not None:
        indptr, indices = tri.vertex_neighbor_vertices
        edges = idx[np.column_stack([np.repeat(np.arange(len(idx)), np.diff(indptr)), indices])]
        length = np.linalg.norm(c.left[edges[:, 0]] - c.left[edges[:, 1]], axis=1)
        failed = _grow(c, edges[np.lexsort((length, edges[:, 0]))], match, taken, params)
        if len(failed) == 0:
            return
        active[failed] = False
        idx = np.flatnonzero(active)
        tri = _triangulation(c.left[idx])


def match_delaunay(left_uv: np.ndarray, right_uv: np.ndarray, calib: StereoCalibration,
                   params: MatchParams = MatchParams()) -> np.ndarray:
    """Prior-guided Delaunay matching (module docstring): pairs (K, 2) of left and right indices."""
    c = candidates(left_uv, right_uv, calib, params)
    tri_l, tri_r = _triangulation(c.left), _triangulation(c.right)
    if tri_l is None or tri_r is None:
        return match_epipolar_nn(left_uv, right_uv, calib, params)
    nn = nn_from_candidates(c)
    good = anchors(c, nn, tri_l, tri_r, params)
    vertices = np.unique(tri_l.simplices[good])
    js, counts = np.unique(nn[vertices], return_counts=True)
    shared = js[counts > 1]  # a right point that anchors claim for two left points: drop those anchors
    good = good[~np.any(np.isin(nn[tri_l.simplices[good]], shared), axis=1)]
    match = np.full(len(c.left), -1)
    vertices = np.unique(tri_l.simplices[good])
    match[vertices] = nn[vertices]
    propagate(c, tri_l, match, params)
    i = np.flatnonzero(match >= 0)
    return np.column_stack([i, match[i]]).astype(np.int64)
