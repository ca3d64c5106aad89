"""Small mesh helpers for the scene (numpy; mm, left camera frame)."""

from __future__ import annotations

import numpy as np
import trimesh


def bonded_faces(vertices: np.ndarray, faces: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """Mask (F,) of the gel's faces on its bonded plane z = min z (facing -z, towards the cameras)."""
    v = np.asarray(vertices, float)
    z0 = v[:, 2].min()
    tri = v[np.asarray(faces)]
    n_z = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2]
    return np.all(np.abs(tri[:, :, 2] - z0) < tol, axis=1) & (n_z < 0)


def box_mesh(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Closed box [lo, hi] with outward normals."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    m = trimesh.creation.box(extents=hi - lo)
    return np.asarray(m.vertices) + (lo + hi) / 2, np.asarray(m.faces)


def rectangle(centre, normal, size, u_axis) -> tuple[np.ndarray, np.ndarray]:
    """Rectangle of ``size`` = (along u, across) mm, two triangles wound counter-clockwise about ``normal``."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    u = np.asarray(u_axis, float) - np.dot(u_axis, n) * n
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    c, a, b = np.asarray(centre, float), size[0] / 2, size[1] / 2
    v = np.array([c - a * u - b * w, c + a * u - b * w, c + a * u + b * w, c - a * u + b * w])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def unit_sphere(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    return np.asarray(m.vertices), np.asarray(m.faces)


def marker_vertices(template: np.ndarray, centres: np.ndarray, radius: float,
                    deformation: np.ndarray | None = None) -> np.ndarray:
    """Vertices (K * Vt, 3) of K markers: c_k + F_k (radius * template)."""
    t = radius * np.asarray(template, float)
    if deformation is None:
        return (np.asarray(centres, float)[:, None, :] + t[None]).reshape(-1, 3)
    return (np.asarray(centres, float)[:, None, :] + np.einsum("kij,vj->kvi", deformation, t)).reshape(-1, 3)


def tile_faces(faces: np.ndarray, n_vertices: int, count: int) -> np.ndarray:
    return (np.asarray(faces)[None] + n_vertices * np.arange(count)[:, None, None]).reshape(-1, 3)


def open_box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Box [lo, hi] without its +z face (a housing open towards the backing), normals inward."""
    v, f = box_mesh(lo, hi)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    keep = ~((n[:, 2] > 0) & np.all(np.isclose(tri[:, :, 2], np.asarray(hi, float)[2]), axis=1))
    return v, f[keep][:, ::-1]
