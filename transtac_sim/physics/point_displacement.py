"""Displacement at points inside the tets (the markers' embedding), as a mixin of ``QuasiStaticSolver`` (solver.py,
which provides the field u, the cells and which tets it re-oriented).

A point is given by its tet (index into the tets as passed to the solver) and barycentric weights of that tet's 4
vertices in the order given; the solver stores tets with a positive volume, swapping vertices 1 and 2 where the input had
a negative one, so the weights are first put in the stored order. u there is exact for the element order used (P1, P2).
"""

from __future__ import annotations

import numpy as np
import warp as wp
import warp.fem as fem


class PointDisplacement:
    """``displacement_at`` for ``QuasiStaticSolver``."""

    def displacement_at(self, tet_index: np.ndarray, barycentric: np.ndarray) -> np.ndarray:
        """(K,3) displacement at points given by tet index (K,) and barycentric weights (K,4) of the tet's
        vertices (in the order of ``tets`` as given), exact for the element order used."""
        tet_index = np.asarray(tet_index, dtype=np.int32)
        b = np.asarray(barycentric, dtype=np.float64)
        if b.shape != (len(tet_index), 4):
            raise ValueError("barycentric must be (K,4)")
        q = self._q_points(tet_index, b)
        out = wp.empty(len(tet_index), dtype=wp.vec3d, device=self.device)
        fem.interpolate(_displacement_form, dest=out, at=q, fields={"u": self.u})
        return out.numpy()

    def _q_points(self, tet_index: np.ndarray, b: np.ndarray) -> fem.PicQuadrature:
        """The points as a quadrature of the solver's cells: each tet's stored vertex order, weights 1-3 as coordinates."""
        coords = np.empty((len(tet_index), 3))
        given = self._given_order(tet_index)
        for k in range(3):
            coords[:, k] = np.take_along_axis(b, given[:, k + 1 : k + 2], axis=1)[:, 0]
        return fem.PicQuadrature(
            self._cells,
            (wp.array(tet_index, dtype=int, device=self.device), wp.array(coords, dtype=wp.vec3d, device=self.device)),
        )

    def _given_order(self, tet_index: np.ndarray) -> np.ndarray:
        """For each stored tet vertex slot, the slot it had in the input tets."""
        order = np.tile(np.arange(4), (len(tet_index), 1))
        flipped = self._flipped[tet_index]
        order[flipped] = order[flipped][:, [0, 2, 1, 3]]
        return order


@fem.integrand
def _displacement_form(s: fem.Sample, u: fem.Field):
    """u (mm) at the sample."""
    return u(s)
