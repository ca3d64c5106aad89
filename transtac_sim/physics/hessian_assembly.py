"""The Hessian of E(u) (assembly.py), summed into the one kept matrix the linear solver receives, as a mixin of
``QuasiStaticSolver`` (which provides the spaces, quadratures, fields and contact state; assembly.py the deviatoric
term, the values the contact and barrier forms take, the barrier flag of the last gradient and the tets as the
tet-by-tet terms see them, ``_deviatoric``, ``_contact_values``, ``_barrier_values``, ``_barrier_acts``, ``_tets``,
``_barrier_check_points``).

- the deviatoric part mu grad du : grad v does not depend on u: it is assembled once (assembly.py ``_deviatoric``), and
  its sparsity, every pair of nodes of an element, is the sum's;
- the volumetric Hessian (one point per tet) is added tet by tet (volumetric_hessian.py), the barrier's only in the
  tets where it acts (barrier_terms.py);
- the contact Hessian is assembled into a kept matrix whose sparsity does not change (``_assemble``: warp.fem's mapped
  construction, values only after the first assembly), over the boundary sides where it can be non-zero
  (contact_sides.py), and its blocks are added at their places in the sum (``_sum_slots``) by one launch instead of a
  sparse matrix sum;
- on a GPU the launches are replayed as a CUDA graph (replay.py).
"""

from __future__ import annotations

import numpy as np
import warp as wp
import warp.fem as fem
from warp.sparse import BsrMatrix

from transtac_sim.physics import contact, elasticity
from transtac_sim.physics.barrier_terms import BarrierHessian
from transtac_sim.physics.sparse_product import block_keys
from transtac_sim.physics.volumetric_hessian import VolumetricHessian


@wp.kernel(enable_backward=False)
def _add_blocks(part: wp.array(dtype=wp.mat33d), slots: wp.array(dtype=int), total: wp.array(dtype=wp.mat33d)):
    """total[slots[k]] += part[k]: a part's blocks added at their places in the sum (each place once per part)."""
    k = wp.tid()
    total[slots[k]] = total[slots[k]] + part[k]


@wp.kernel(enable_backward=False)
def _stiff_points(k_normal: wp.array(dtype=wp.float64), k_slip: wp.array(dtype=wp.float64),
                  k_slip_dir: wp.array(dtype=wp.float64), count: int, stiff: wp.array(dtype=wp.int8)):
    """stiff[q] = 1 where any indenter has a normal or friction stiffness at contact quadrature point q."""
    q = wp.tid()
    stiff[q] = wp.where(contact.stiff_at(k_normal, k_slip, k_slip_dir, count, q), wp.int8(1), wp.int8(0))


class HessianAssembly:
    """The Newton Hessian for ``QuasiStaticSolver``."""

    def _hessian(self, ind, geometric: float, clamp: int = elasticity.CLAMPED) -> BsrMatrix:
        """The Hessian at self.u, where the last ``_gradient`` was evaluated (whose contact state and barrier flag it
        takes), summed into one kept matrix with the elements' whole sparsity (``self._H``: the
        linear solver may change it in place; the next call overwrites it); ``geometric`` and ``clamp`` select the
        volumetric term's geometric part (elasticity.py). On a GPU its launches are replayed as a CUDA graph per
        field, indenter struct, contact stiffness, (geometric, clamp), barrier flag and contact side subset
        (replay.py); the subset is found first, on the host.

        The deviatoric part mu grad du : grad v does not depend on u: it is assembled once and is the sum's start;
        the volumetric part is added tet by tet (volumetric_hessian.py), the barrier's only in the tets where it acts
        (barrier_terms.py), the contact part through its blocks' places in the sum (``_sum_slots``), one launch
        instead of a sparse matrix sum."""
        subset = self._contact_subset(ind) if ind.count else None
        key = ("hessian", self.u.dof_values.ptr, id(ind), float(ind.stiffness), float(geometric), int(clamp),
               self._barrier_acts, id(subset))
        self._graphs.run(key, (self.u, ind, subset), lambda: self._hessian_terms(ind, geometric, clamp, subset))
        return self._H

    def _hessian_terms(self, ind, geometric: float, clamp: int, subset) -> None:
        """The Hessian's parts summed into ``self._H`` (launches only, but for the kept matrices, places and set-up
        made on first use); ``subset``: the contact sides to integrate over, or None."""
        H_dev = self._deviatoric().H
        if self._H is None:
            self._H = wp.sparse.bsr_copy(H_dev)
        parts = {}
        hessian = {"geometric": geometric, "clamp": int(clamp), "barrier_tets": self._barrier_tets}
        self._barrier_tets.zero_()
        if self._barrier_acts:  # some det F is below the barrier's threshold at the last ``_gradient``'s u, this one:
            # first, since it marks the tets where the barrier acts, whose clamped pressure is halved
            fem.interpolate(elasticity.barrier_state_form, at=self._q_det, fields={"u": self.u},
                            values=self._barrier_values() | {"F_qp": self._F_det, "b_qp": self._b_det} | hessian)
        if subset is not None:
            parts["contact"] = self._assemble(
                "contact", contact.contact_hessian_form, subset.quadrature, {"du": subset.trial, "v": subset.test},
                self._contact_values(ind) | {"qp_base": subset.qp_base, "points": subset.points})
        H = self._H
        wp.copy(H.values, H_dev.values, count=H_dev.nnz)
        if self._volumetric is None:
            self._volumetric = VolumetricHessian.make(self._tets(), H, self.device)
        self._volumetric.add_to(H, self.u.dof_values, self._params, geometric, clamp, self._barrier_tets)
        if self._barrier_acts:  # in the tets it marked (barrier_terms.py)
            if self._barrier_hessian is None:
                self._barrier_hessian = BarrierHessian.make(self._barrier_check_points(), H, self.device)
            self._barrier_hessian.add_to(H, self._F_det, self._b_det, self._barrier_tets)
        for name, part in parts.items():
            self._add_part(H, name, part)

    def _add_part(self, H: BsrMatrix, name: str, part: BsrMatrix) -> None:
        """H's blocks += the part ``name``'s, each at its place in H (``_sum_slots``; one launch)."""
        slots = self._sum_slots(name, part)
        wp.launch(_add_blocks, dim=len(slots), device=self.device, inputs=[part.values, slots, H.values])

    def _contact_subset(self, ind):
        """The contact sides the Hessian is integrated over (contact_sides.py: those with a normal or friction
        stiffness in the contact state of the last ``_gradient``, and their neighbours), or None where there are none;
        where the subset is made anew, its matrix and places in the sum are dropped (made again on first use). On a GPU,
        where the caller has read ``_gradient``'s coverage flag (``contact_stale_read``: the subset still holds), the
        kept subset with no read of its own."""
        sides = self._contact_sides
        if sides.current is not None and self._contact_stale is False:
            return None if sides.current.quadrature is None else sides.current
        st = self._contact_state
        points = self._q_contact.total_point_count()
        stiff = self._stiff_work
        wp.launch(_stiff_points, dim=points, device=self.device,
                  inputs=[st.k_normal, st.k_slip, st.k_slip_dir, ind.count, stiff])
        if sides.update(stiff.numpy().astype(bool)):
            self._H_parts.pop("contact", None)
            self._H_slots.pop("contact", None)
            self._graphs.clear("hessian")  # they integrate over the old subset, into its matrix
        self._contact_stale = False
        subset = sides.current
        return None if subset.quadrature is None else subset  # None: nothing touches

    def _assemble(self, name: str, form, quadrature, fields: dict, values: dict) -> BsrMatrix:
        """A Hessian part, assembled into the same matrix each time (``self._H_parts[name]``). Its sparsity does not
        change between Newton iterations, so after the first assembly warp.fem's mapped construction skips the
        topology (the sort of every element's triplets) and scatters values only: atomically on the CPU (serial,
        deterministic; 1.7x faster there), through the kept triplet-to-block map on a GPU (deterministic order)."""
        H = self._H_parts.get(name)
        construction = "mapped" if self.device.is_cuda else "mapped_atomic"
        if H is None:
            H = fem.integrate(form, quadrature=quadrature, fields=fields, values=values, output_dtype=wp.float64,
                              bsr_options={"construction": construction, "capacity": "auto"})
            H.nnz_sync()
            self._H_parts[name] = H
        else:
            fem.integrate(form, quadrature=quadrature, fields=fields, values=values, output=H,
                          bsr_options={"construction": construction, "capacity": "reuse"})
        return H

    def _sum_slots(self, name: str, part: BsrMatrix) -> wp.array:
        """For each block of the part ``name``, its index among the sum's blocks (made once: a part's sparsity is
        kept, ``_assemble``). Every part's blocks couple nodes of one element, so each has a place in the deviatoric
        part's sparsity, which is the sum's."""
        slots = self._H_slots.get(name)
        if slots is None:
            into, own = self._deviatoric().keys, block_keys(part)  # the sum's kept: read back once, not per subset
            index = np.searchsorted(into, own)  # a BSR matrix's blocks are sorted by row, then column
            if np.any(index >= len(into)) or np.any(into[np.minimum(index, len(into) - 1)] != own):
                raise RuntimeError(f"the {name} Hessian has a block outside the elements' sparsity")
            slots = self._H_slots[name] = wp.array(index.astype(np.int32), dtype=int, device=self.device)
        return slots
