"""Tet mesh quality: dihedral angles and aspect ratio.

Aspect ratio here is the normalised one, longest edge / (2 sqrt(6) inradius): 1 for a regular tet,
growing without bound as a tet flattens. Dihedral angles are in degrees (regular tet: 70.53).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

_EDGES = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
# For edge (i, j), the two faces meeting there are opposite the other two vertices k, l.
_FACES = [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]


@dataclass(frozen=True)
class MeshQuality:
    tets: int
    vertices: int
    min_dihedral_deg: float
    max_dihedral_deg: float
    max_aspect_ratio: float
    mean_aspect_ratio: float
    min_volume_mm3: float

    def as_dict(self) -> dict:
        return asdict(self)


def dihedral_angles_deg(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """(M, 6) dihedral angles at the six edges of each tet, degrees."""
    p = vertices[tets]  # (M, 4, 3)
    normals = []
    for f in _FACES:  # outward normals of the four faces (face i is opposite vertex i)
        a, b, c = p[:, f[0]], p[:, f[1]], p[:, f[2]]
        n = np.cross(b - a, c - a)
        normals.append(n / np.linalg.norm(n, axis=1, keepdims=True))
    out = np.empty((len(tets), 6))
    for e, (i, j) in enumerate(_EDGES):
        k, m = [x for x in range(4) if x not in (i, j)]
        cos = -np.einsum("ij,ij->i", normals[k], normals[m])
        out[:, e] = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return out


def aspect_ratios(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    p = vertices[tets]
    vol = np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])) / 6
    area = sum(np.linalg.norm(np.cross(p[:, f[1]] - p[:, f[0]], p[:, f[2]] - p[:, f[0]]), axis=1) / 2 for f in _FACES)
    inradius = 3 * vol / area
    longest = np.max([np.linalg.norm(p[:, i] - p[:, j], axis=1) for i, j in _EDGES], axis=0)
    with np.errstate(divide="ignore"):
        return longest / (2 * np.sqrt(6) * inradius)


def mesh_quality(vertices: np.ndarray, tets: np.ndarray) -> MeshQuality:
    dih = dihedral_angles_deg(vertices, tets)
    ar = aspect_ratios(vertices, tets)
    p = vertices[tets]
    vol = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6
    return MeshQuality(len(tets), len(vertices), float(dih.min()), float(dih.max()), float(ar.max()),
                       float(ar.mean()), float(vol.min()))
