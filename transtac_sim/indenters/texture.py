"""Surface textures of indenters: colour patterns fixed to the body, for dense stereo to find features on.

``speckle_albedo`` is 3D value noise of the vertices' positions in the indenter's own (mesh file) frame:
random values on a cubic lattice of spacing ``scale_mm`` (a hash of the lattice point and ``seed``),
interpolated trilinearly with smoothstep weights, then stretched to full contrast and mapped to an albedo
between ``floor`` and 1 times the indenter's colour. Being a function of rest positions, the pattern moves
with the body; being per vertex, it is only as fine as the mesh (edges well under ``scale_mm``).
"""

from __future__ import annotations

import numpy as np


def _lattice_value(ijk: np.ndarray, seed: int) -> np.ndarray:
    """Uniform [0, 1) value of each integer lattice point (N, 3), a fixed hash of the point and ``seed``."""
    h = (ijk.astype(np.int64) * np.array([73856093, 19349663, 83492791])).sum(axis=1) ^ (seed * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFFFF) / float(0x1000000)


def speckle_albedo(vertices_mm: np.ndarray, rgb, scale_mm: float, seed: int = 0, floor: float = 0.15) -> np.ndarray:
    """Per-vertex albedo (V, 3) of a speckle of feature size ``scale_mm`` over vertices (V, 3) in mm."""
    x = np.asarray(vertices_mm, float) / scale_mm
    i0 = np.floor(x).astype(np.int64)
    f = x - i0
    w = f * f * (3.0 - 2.0 * f)
    value = np.zeros(len(x))
    for corner in np.ndindex(2, 2, 2):
        c = np.array(corner)
        weight = np.prod(np.where(c == 1, w, 1.0 - w), axis=1)
        value += weight * _lattice_value(i0 + c, seed)
    lo, hi = np.percentile(value, [5, 95]) if len(value) else (0.0, 1.0)
    value = np.clip((value - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
    return (floor + (1.0 - floor) * value)[:, None] * np.asarray(rgb, float)[None]
