"""Tetrahedral mesh of the gel block, fine under the contact region (fTetWild via pytetwild).

The gel fills [-w/2, w/2] x [-h/2, h/2] x [0, t] in the gel frame (mm). The target edge length is
``contact_edge_mm`` over the contact region's xy rectangle (through the whole thickness: the gel is thin)
and grows linearly to ``edge_mm`` over a distance of ``edge_mm`` outside it; pytetwild reads that sizing
field from a background tet mesh. fTetWild keeps the surface within a small envelope of the input box;
vertices within that envelope of a face are snapped onto it, so the bonded face is exactly z = 0.
"""

from __future__ import annotations

import contextlib
import tempfile
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import Delaunay

#: Rectangle (x0, y0, x1, y1) in the gel frame, mm.
Rect = tuple[float, float, float, float]


@dataclass(frozen=True)
class GelMesh:
    vertices_mm: np.ndarray  # (N, 3) float64, gel frame
    tets: np.ndarray  # (M, 4) int32, positively oriented

    @property
    def bonded_vertices(self) -> np.ndarray:
        """Indices of the vertices on the bonded face z = 0."""
        return np.flatnonzero(self.vertices_mm[:, 2] == 0.0)

    def boundary_faces(self) -> np.ndarray:
        """(F, 3) triangles on the mesh boundary, wound outward."""
        t = self.tets
        faces = np.concatenate([t[:, [1, 2, 3]], t[:, [0, 3, 2]], t[:, [0, 1, 3]], t[:, [0, 2, 1]]])
        key = np.sort(faces, axis=1)
        _, idx, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
        return faces[idx[counts == 1]]


def signed_volumes(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    a, b, c, d = (vertices[tets[:, i]] for i in range(4))
    return np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) / 6.0


def sizing_field(size_mm: tuple[float, float, float], region: Rect | None, edge_mm: float,
                 contact_edge_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Background tet mesh (vertices, tets, target edge length per vertex) covering the gel."""
    w, h, t = size_mm
    step = max(contact_edge_mm, min(w, h) / 64)
    xs = np.arange(-w / 2 - step, w / 2 + 2 * step, step)
    ys = np.arange(-h / 2 - step, h / 2 + 2 * step, step)
    zs = np.array([-1.0, t / 2, t + 1.0])
    P = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)
    if region is None:
        values = np.full(len(P), edge_mm)
    else:
        x0, y0, x1, y1 = region
        dx = np.maximum.reduce([x0 - P[:, 0], P[:, 0] - x1, np.zeros(len(P))])
        dy = np.maximum.reduce([y0 - P[:, 1], P[:, 1] - y1, np.zeros(len(P))])
        ramp = np.clip(np.hypot(dx, dy) / edge_mm, 0.0, 1.0)
        values = contact_edge_mm + ramp * (edge_mm - contact_edge_mm)
    return P, Delaunay(P).simplices.astype(np.int32), values


def tetrahedralize_gel(size_mm: tuple[float, float, float], region: Rect | None, edge_mm: float,
                       contact_edge_mm: float) -> GelMesh:
    """Mesh the gel block; see the module docstring for the sizing and the snapping."""
    import pytetwild  # imports pyvista and VTK: slow, so only when a mesh is actually built

    w, h, t = size_mm
    box = trimesh.creation.box((w, h, t))
    box.apply_translation((0, 0, t / 2))
    bg_v, bg_t, bg_val = sizing_field(size_mm, region, edge_mm, contact_edge_mm)
    with tempfile.TemporaryDirectory() as tmp, contextlib.chdir(tmp):  # fTetWild drops a file in the cwd
        v, tets = pytetwild.tetrahedralize(
            box.vertices, box.faces.astype(np.int32), edge_length_abs=edge_mm,
            bg_vertices=bg_v, bg_tets=bg_t, bg_values=bg_val, quiet=True, num_threads=0,
        )
    v = np.asarray(v, dtype=np.float64)
    envelope = 1e-3 * np.linalg.norm([w, h, t])
    for axis, planes in ((0, (-w / 2, w / 2)), (1, (-h / 2, h / 2)), (2, (0.0, t))):
        for p in planes:
            v[np.abs(v[:, axis] - p) <= envelope, axis] = p
    tets = np.asarray(tets, dtype=np.int32)
    neg = signed_volumes(v, tets) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return GelMesh(v, tets)
