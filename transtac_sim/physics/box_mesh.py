"""Structured tet meshes of boxes, optionally graded (fine where the contact is, coarse far away).

The box [x0, x1] x [y0, y1] x [z0, z1] (mm) is cut into hexahedra along 1-D coordinate lists and each
hexahedron into 6 tets sharing its main diagonal (Kuhn split), which is conforming across hexahedra.
``graded_coordinates`` returns a list with spacing ``h_fine`` on [a, b] that grows geometrically by
``growth`` per cell towards both ends of [lo, hi].
"""

from __future__ import annotations

import numpy as np

_KUHN = np.array([[0, 1, 3, 7], [0, 1, 5, 7], [0, 2, 3, 7], [0, 2, 6, 7], [0, 4, 5, 7], [0, 4, 6, 7]])


def graded_coordinates(lo: float, hi: float, h_fine: float, fine_lo: float, fine_hi: float,
                       growth: float = 1.5) -> np.ndarray:
    """Sorted coordinates from lo to hi: uniform ``h_fine`` on [fine_lo, fine_hi], growing outside."""
    fine_lo, fine_hi = max(lo, fine_lo), min(hi, fine_hi)
    n = max(1, int(np.ceil((fine_hi - fine_lo) / h_fine - 1e-9)))
    coords = list(np.linspace(fine_lo, fine_hi, n + 1))

    def grow(start: float, end: float, sign: float) -> list[float]:
        out, x, h = [], start, h_fine
        while sign * (end - x) > 1e-9:
            h *= growth
            x_next = x + sign * h
            if sign * (end - x_next) < 0.5 * h:  # last cell: stretch to the end
                x_next = end
            out.append(x_next)
            x = x_next
        return out

    coords = grow(fine_lo, lo, -1.0)[::-1] + coords + grow(fine_hi, hi, 1.0)
    return np.array(coords)


def box_tet_mesh(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (N,3) float64 and positively oriented tets (M,4) int32 of the box on the grid xs x ys x zs."""
    nx, ny, nz = len(xs), len(ys), len(zs)
    X, Y, Z = np.meshgrid(xs, ys, zs, indexing="ij")
    vertices = np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)
    i, j, k = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1), np.arange(nz - 1), indexing="ij")
    base = (i * ny + j) * nz + k
    corners = np.stack([base + dx * ny * nz + dy * nz + dz
                        for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], axis=-1).reshape(-1, 8)
    # corner c = 4 dx + 2 dy + dz; Kuhn paths go from corner 0 to corner 7
    tets = corners[:, _KUHN].reshape(-1, 4).astype(np.int32)
    e = vertices[tets[:, 1:]] - vertices[tets[:, :1]]
    neg = np.einsum("ij,ij->i", np.cross(e[:, 0], e[:, 1]), e[:, 2]) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return vertices, tets


def gel_block(width: float, height: float, thickness: float, h_fine: float, fine_half_width: float,
              growth: float = 1.5, h_fine_z: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gel-frame block x in [-W/2, W/2], y in [-H/2, H/2], z in [0, T], fine near the centre of the top."""
    xs = graded_coordinates(-width / 2, width / 2, h_fine, -fine_half_width, fine_half_width, growth)
    ys = graded_coordinates(-height / 2, height / 2, h_fine, -fine_half_width, fine_half_width, growth)
    zs = graded_coordinates(0.0, thickness, h_fine_z or h_fine, thickness - fine_half_width, thickness, growth)
    return box_tet_mesh(xs, ys, zs)
