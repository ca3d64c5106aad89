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

    def warp_mesh(self, device) -> wp.Mesh:
        key = str(device)
        if key not in self._meshes:
            self._meshes[key] = wp.Mesh(
                points=wp.array(self.vertices_mm.astype(np.float32), dtype=wp.vec3, device=device),
                indices=wp.array(self.faces.reshape(-1), dtype=wp.int32, device=device),
                support_winding_number=True,
            )
        return self._meshes[key]
