"""The boundary sides that the contact Hessian is integrated over: where it can be non-zero, not the whole surface.

Contact's energy, gradient and state are integrated over every side an indenter can touch (solver.py
``_touchable_sides``), but its Hessian is zero at every quadrature point without a normal or friction stiffness (the
contact state, contact.py ``ContactState``), which is all but a small patch under the indenter: integrated over these
sides only, a Newton Hessian of the tiny press fixture took 18 instead of 35 ms on the 2-core CPU
(scripts/fem_phase_profile.py, BENCHMARKS.md ``fem_host_path_cpu``).

``ContactSides.update`` finds the sides with such a point, adds the sides that share a vertex with them (contact
spreads between Newton iterations), and keeps the subset while it holds them all; where contact reaches beyond it,
it is made anew (its union with the old one, unless that is over twice what is needed), and the caller assembles the
contact Hessian's matrix and its places in the sum anew too. The subset's quadrature numbers its points
``element * points + k`` over its own sides (warp.fem's ``RegularQuadrature``); ``qp_base`` maps them to the full
quadrature's numbering, which the contact state uses: ``qp_base[element] + k``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import warp as wp
import warp.fem as fem


@dataclass(frozen=True)
class SideSubset:
    """The chosen sides; without any (nothing touches) every field but ``mask`` and ``points`` is None."""

    mask: np.ndarray  # bool, one per touchable side
    quadrature: fem.RegularQuadrature | None
    trial: fem.Field | None
    test: fem.Field | None
    qp_base: wp.array | None  # (subset sides,) int: the full quadrature's index of each subset side's first point
    points: int  # quadrature points per side


class ContactSides:
    """The subset of ``sides`` (the touchable sides, whose vertex indices are ``side_vertices``, (sides, 3)) that the
    contact Hessian is integrated over, for a quadrature of ``order`` on ``space``."""

    def __init__(self, space, sides: fem.GeometryDomain, side_vertices: np.ndarray, order: int, device):
        self._space, self._sides, self._order, self._device = space, sides, order, device
        incidence = sp.csr_matrix((np.ones(side_vertices.size), side_vertices.reshape(-1),
                                   np.arange(0, side_vertices.size + 1, 3)))
        self._neighbours = (incidence @ incidence.T).tocsr()  # sides sharing a vertex (and each side itself)
        self.current: SideSubset | None = None

    def update(self, stiff: np.ndarray) -> bool:
        """``stiff``: bool per quadrature point of the full contact quadrature (any indenter). True if the subset was
        made anew (the caller's matrix for it is then out of date); ``current`` is set after the first call."""
        points = len(stiff) // self._neighbours.shape[0]
        touching = stiff.reshape(-1, points).any(axis=1).astype(np.float64)
        needed = (self._neighbours @ touching) > 0.0
        if self.current is not None and not np.any(needed & ~self.current.mask):
            return False
        mask = needed
        if self.current is not None and np.count_nonzero(needed | self.current.mask) <= 2 * np.count_nonzero(needed):
            mask = needed | self.current.mask
        self.current = self._subset(mask, points)
        return True

    def _subset(self, mask: np.ndarray, points: int) -> SideSubset:
        if not mask.any():
            return SideSubset(mask, None, None, None, None, points)
        chosen = np.flatnonzero(mask)
        with wp.ScopedDevice(self._device):
            domain = fem.Subdomain(self._sides, element_indices=wp.array(chosen.astype(np.int32), dtype=int))
            quadrature = fem.RegularQuadrature(domain, order=self._order)
            base = wp.array((chosen * points).astype(np.int32), dtype=int)
            return SideSubset(mask, quadrature, fem.make_trial(self._space, domain=domain),
                              fem.make_test(self._space, domain=domain), base, points)
