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

On a GPU the host would read the contact state back at every Newton Hessian only to learn that the subset still holds
(the usual case), and each new subset makes its matrix, its places in the sum and the Hessian's CUDA graphs anew while
the GPU waits (press_slide on an H100: the contact state read at 164 Hessians over frames 1-9;
scripts/fem_host_census.py). There ``launch_coverage`` tests on the device whether the subset still holds every stiff
side's neighbours (one flag, which Newton reads with the gradient's norm: the contact state read at 3 Hessians), and a
new subset takes ``rings`` rings of neighbours around the stiff sides instead of one, so that contact moving across
the surface stays inside it longer (press_slide frames 1-9 in 1.15-1.27 s against 1.25-1.56 s with one ring,
BENCHMARKS.md ``fem_folded_reads_gpu``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import warp as wp
import warp.fem as fem

from transtac_sim.physics.contact import stiff_at


@dataclass(frozen=True)
class SideSubset:
    """The chosen sides; without any (nothing touches) every field but ``mask`` and ``points`` is None."""

    mask: np.ndarray  # bool, one per touchable side
    quadrature: fem.RegularQuadrature | None
    trial: fem.Field | None
    test: fem.Field | None
    qp_base: wp.array | None  # (subset sides,) int: the full quadrature's index of each subset side's first point
    points: int  # quadrature points per side


#: rings of neighbours a new subset takes around the stiff sides on a GPU (on the CPU 1: there each side costs the
#: Hessian's time, and a new subset little)
CONTACT_RINGS_GPU = 2


@wp.kernel(enable_backward=False)
def _uncovered(k_normal: wp.array(dtype=wp.float64), k_slip: wp.array(dtype=wp.float64),
               k_slip_dir: wp.array(dtype=wp.float64), count: int, points: int, inner: wp.array(dtype=wp.int8),
               flag: wp.array(dtype=wp.float64)):
    """flag[0] = 1 where contact quadrature point q has a normal or friction stiffness (any indenter) on a side outside
    ``inner`` (the sides whose neighbours are all in the subset); left as it is elsewhere (0 from the caller)."""
    q = wp.tid()
    if inner[q // points] == wp.int8(0) and stiff_at(k_normal, k_slip, k_slip_dir, count, q):
        flag[0] = wp.float64(1.0)


class ContactSides:
    """The subset of ``sides`` (the touchable sides, whose vertex indices are ``side_vertices``, (sides, 3)) that the
    contact Hessian is integrated over, for a quadrature of ``order`` on ``space``; a new subset takes ``rings`` rings
    of neighbours around the stiff sides (at least 1; default ``CONTACT_RINGS_GPU`` on a GPU, else 1)."""

    def __init__(self, space, sides: fem.GeometryDomain, side_vertices: np.ndarray, order: int, device,
                 rings: int | None = None):
        rings = rings if rings is not None else CONTACT_RINGS_GPU if wp.get_device(device).is_cuda else 1
        if rings < 1:
            raise ValueError(f"rings must be >= 1 (the stiff sides' neighbours), got {rings}")
        self._space, self._sides, self._order, self._device, self._rings = space, sides, order, device, rings
        incidence = sp.csr_matrix((np.ones(side_vertices.size), side_vertices.reshape(-1),
                                   np.arange(0, side_vertices.size + 1, 3)))
        self._neighbours = (incidence @ incidence.T).tocsr()  # sides sharing a vertex (and each side itself)
        self.current: SideSubset | None = None
        # 1 on the sides all of whose neighbours are in the current subset (``launch_coverage``), on the device
        self._inner = wp.zeros(self._neighbours.shape[0], dtype=wp.int8, device=device)
        self.stale = wp.zeros(1, dtype=wp.float64, device=device)  # ``launch_coverage``'s flag

    def update(self, stiff: np.ndarray) -> bool:
        """``stiff``: bool per quadrature point of the full contact quadrature (any indenter). True if the subset was
        made anew (the caller's matrix for it is then out of date); ``current`` is set after the first call."""
        points = len(stiff) // self._neighbours.shape[0]
        touching = stiff.reshape(-1, points).any(axis=1).astype(np.float64)
        needed = (self._neighbours @ touching) > 0.0
        if self.current is not None and not np.any(needed & ~self.current.mask):
            return False
        for _ in range(self._rings - 1):
            needed = (self._neighbours @ needed.astype(np.float64)) > 0.0
        mask = needed
        if self.current is not None and np.count_nonzero(needed | self.current.mask) <= 2 * np.count_nonzero(needed):
            mask = needed | self.current.mask
        self.current = self._subset(mask, points)
        outside = (~mask).astype(np.float64)
        self._inner.assign(((self._neighbours @ outside) == 0.0).astype(np.int8))
        return True

    def launch_coverage(self, k_normal: wp.array, k_slip: wp.array, k_slip_dir: wp.array, count: int,
                        total_points: int) -> None:
        """``stale`` = 1 where ``update`` with this contact state (the stiffnesses of ``count`` indenters at each of the
        ``total_points`` quadrature points over every side, contact.py ``ContactState``: index q * count + i) would make
        a new subset, else 0: launched only, for a read of the caller's (graph-capturable; before the first ``update``
        every stiff point makes it 1)."""
        points = total_points // self._neighbours.shape[0]
        self.stale.zero_()
        wp.launch(_uncovered, dim=total_points, device=self._device,
                  inputs=[k_normal, k_slip, k_slip_dir, count, points, self._inner, self.stale])

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
