"""Rigid indenters: a watertight triangle mesh (local frame, mm) and a Coulomb friction coefficient."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp


@dataclass
class RigidIndenter:
    """A rigid body that touches the gel; ``pose`` matrices map its local frame to the gel frame."""

    name: str
    vertices_mm: np.ndarray
    faces: np.ndarray
    friction: float = 0.0
    _meshes: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        self.vertices_mm = np.ascontiguousarray(self.vertices_mm, dtype=np.float64)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32)
        if self.vertices_mm.ndim != 2 or self.vertices_mm.shape[1] != 3 or self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"indenter {self.name!r}: vertices must be (N,3) and faces (M,3)")
        if self.friction < 0.0:
            raise ValueError(f"indenter {self.name!r}: friction must be >= 0, got {self.friction}")
        edges = np.sort(self.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        if np.any(counts != 2):
            raise ValueError(f"indenter {self.name!r}: mesh is not watertight ({int(np.sum(counts != 2))} open edges)")

    @classmethod
    def from_trimesh(cls, name: str, mesh, friction: float = 0.0) -> RigidIndenter:
        return cls(name, np.asarray(mesh.vertices), np.asarray(mesh.faces), friction)

    @property
    def bounding_radius_mm(self) -> float:
        """Largest distance from the local origin to a vertex."""
        return float(np.max(np.linalg.norm(self.vertices_mm, axis=1)))

    def lowest_z(self, pose: np.ndarray) -> float:
        """Lowest gel-frame z of the mesh at ``pose``."""
        return float(np.min(self.vertices_mm @ pose[:3, :3].T[:, 2] + pose[2, 3]))

    def feature_normals(self) -> np.ndarray:
        """(faces, 7, 3) float64, local frame: each face's unit outward normal, then the angle-weighted pseudo-normals
        (Baerentzen & Aanaes 2005) of its vertices 0-2 (the incident faces' normals weighted by their angles there) and
        of its edges opposite vertices 0-2 (the sum of the two faces' normals), normalised; 0 where that sum is 0
        (a knife edge or a degenerate vertex). For a closed mesh, a point p whose closest mesh point c lies inside a
        feature is outside exactly where (p - c) . (the feature's pseudo-normal) > 0 (indenter_query.py ``penetration``)."""
        P = self.vertices_mm[self.faces]  # (faces, 3 corners, 3)
        cross = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
        face_normal = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-300)
        vertex_sum = np.zeros_like(self.vertices_mm)
        for k in range(3):
            a, b = P[:, (k + 1) % 3] - P[:, k], P[:, (k + 2) % 3] - P[:, k]
            cos = np.einsum("fi,fi->f", a, b) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
            np.add.at(vertex_sum, self.faces[:, k], np.arccos(np.clip(cos, -1.0, 1.0))[:, None] * face_normal)
        edges = np.sort(np.stack([self.faces[:, [1, 2, 0]], self.faces[:, [2, 0, 1]]], axis=2).reshape(-1, 2), axis=1)
        _, edge_index = np.unique(edges, axis=0, return_inverse=True)  # edge opposite corner k of face f: 3 f + k
        edge_sum = np.zeros((int(edge_index.max()) + 1, 3))
        np.add.at(edge_sum, edge_index.reshape(-1), np.repeat(face_normal, 3, axis=0))

        def unit(v: np.ndarray) -> np.ndarray:
            length = np.linalg.norm(v, axis=-1, keepdims=True)
            return np.where(length > 1e-12, v / np.maximum(length, 1e-300), 0.0)

        return np.concatenate([face_normal[:, None], unit(vertex_sum[self.faces]),
                               unit(edge_sum[edge_index.reshape(-1, 3)])], axis=1)

    def warp_mesh(self, device) -> wp.Mesh:
        key = str(device)
        if key not in self._meshes:
            self._meshes[key] = wp.Mesh(
                points=wp.array(self.vertices_mm.astype(np.float32), dtype=wp.vec3, device=device),
                indices=wp.array(self.faces.reshape(-1), dtype=wp.int32, device=device),
                support_winding_number=True,
            )
        return self._meshes[key]
