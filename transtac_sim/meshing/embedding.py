"""Embedding points (marker centres) in a tet mesh: element index + barycentric coordinates.

A point p in tet (x0, x1, x2, x3) has barycentric coordinates b with p = sum_i b_i x_i, sum_i b_i = 1,
all b_i >= 0. Once embedded, the point follows any displacement field u given at the vertices:
p' = sum_i b_i (x_i + u_i), which is exact for fields that are linear over each tet (affine motions,
P1 finite-element solutions).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree


@dataclass(frozen=True)
class Embedding:
    tet_index: np.ndarray  # (K,) int64
    barycentric: np.ndarray  # (K, 4) float64

    def interpolate(self, tets: np.ndarray, vertex_values: np.ndarray) -> np.ndarray:
        """Values at the embedded points of a per-vertex field (positions, displacements...)."""
        corners = vertex_values[tets[self.tet_index]]  # (K, 4, D)
        return np.einsum("kc,kcd->kd", self.barycentric, corners)


def barycentric(vertices: np.ndarray, tets: np.ndarray, tet_index: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(K, 4) barycentric coordinates of ``points`` in the tets ``tet_index``."""
    p = vertices[tets[tet_index]]  # (K, 4, 3)
    A = (p[:, 1:] - p[:, :1]).transpose(0, 2, 1)  # columns x1 - x0, x2 - x0, x3 - x0
    b123 = np.linalg.solve(A, (points - p[:, 0])[..., None])[..., 0]
    return np.column_stack([1.0 - b123.sum(axis=1), b123])


def embed_points(vertices: np.ndarray, tets: np.ndarray, points: np.ndarray, *, candidates: int = 48,
                 tolerance: float = 1e-9) -> Embedding:
    """Find the tet containing each point (searching the tets with the nearest centroids, then all)."""
    points = np.atleast_2d(np.asarray(points, dtype=np.float64))
    tree = cKDTree(vertices[tets].mean(axis=1))
    k = min(candidates, len(tets))
    _, near = tree.query(points, k=k)
    near = near.reshape(len(points), k)
    tet_index = np.full(len(points), -1, dtype=np.int64)
    bary = np.zeros((len(points), 4))
    for j in range(k):
        todo = np.flatnonzero(tet_index < 0)
        if len(todo) == 0:
            break
        b = barycentric(vertices, tets, near[todo, j], points[todo])
        ok = b.min(axis=1) >= -tolerance
        tet_index[todo[ok]], bary[todo[ok]] = near[todo[ok], j], b[ok]
    for i in np.flatnonzero(tet_index < 0):  # rare: a sliver far from its centroid; check every tet
        b = barycentric(vertices, tets, np.arange(len(tets)), np.repeat(points[i : i + 1], len(tets), axis=0))
        best = int(np.argmax(b.min(axis=1)))
        if b[best].min() < -tolerance:
            raise ValueError(f"point {i} at {points[i].tolist()} mm lies outside the mesh")
        tet_index[i], bary[i] = best, b[best]
    return Embedding(tet_index, bary)
