"""The energy E(u) of solver.py and its gradient (Warp FEM assembly), and the reductions Newton reads (|g|, the
smallest det F), as a mixin of ``QuasiStaticSolver`` (which provides the spaces, quadratures, fields and contact state);
the Hessian is hessian_assembly.py's.

E(u) = E_el(u) + E_barrier(u) + E_contact(u) (elasticity.py, contact.py), u the displacement (mm), E in N mm:

- the deviatoric term is quadratic in u: its Hessian H_dev is assembled once, and its energy and gradient are products
  with it (``_deviatoric``) instead of integrations at 4 points per tet; H_dev's sparsity is the summed Hessian's;
- the barrier's gradient and Hessian are skipped where every det F is above its threshold (its energy is 0; on a GPU
  the gradient's kernel returns at once in each tet whose check points all have det F >= j_hat, barrier_terms.py, so
  that the energy need not be read first);
- host reads are few: E(u) is summed on the device and read once per evaluation (``_energy``), the smallest det F, the
  largest penetration (contact_records.py) and max |u - u_lag| for friction's lag test are reduced there
  (reductions.py), and so are the contact Hessian's stiff points (hessian_assembly.py; with the fixed dofs' projection
  on the blocks it changes only, device_linear.py: press_slide frames 1-9 on an H100 1.15-1.2x faster in three of four
  runs, then 0.91-0.98x the time again; BENCHMARKS.md ``fem_host_reads_gpu``); on a GPU Newton reads
  the barrier's energy, the contact side subset's coverage and E with the gradient's norm (``barrier_energy_read``,
  ``contact_stale_read``, newton.py ``_read_gradient``), and the line search E with det F, in one read each
  (BENCHMARKS.md ``fem_folded_reads_gpu``);
- contact is integrated over the boundary sides an indenter can touch (solver.py ``_touchable_sides``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
import warp as wp
import warp.fem as fem
from warp.sparse import BsrMatrix

from transtac_sim.physics import contact, elasticity
from transtac_sim.physics.barrier_terms import BarrierCheckPoints
from transtac_sim.physics.cg_kernels import add_dot
from transtac_sim.physics.reductions import (
    launch_extremes,
    launch_negated_free_and_load,
    read_extremes,
    read_negated_free,
)
from transtac_sim.physics.sparse_product import block_keys, block_row_operator
from transtac_sim.physics.volumetric_hessian import TetGeometry


class DeviatoricTerm(NamedTuple):
    """The deviatoric term's constant parts (``Assembly._deviatoric``)."""

    H: BsrMatrix  # int mu grad du : grad v, every dof (the fixed ones too)
    c: wp.array  # int mu I : grad v, its gradient at u = 0 (vec3d per node)
    product: object  # H's matrix-vector product (sparse_product.py)
    work: wp.array  # a buffer like c
    # row * ncol + column of each of H's blocks, in storage order: the sum's sparsity (hessian_assembly.py ``_sum_slots``)
    keys: np.ndarray


class Assembly:
    """Energy and gradient for ``QuasiStaticSolver``."""

    def _contact_fields(self, u):
        return {"u": u.trace(), "u_prev": self.u_prev.trace()}

    def _contact_values(self, ind) -> dict:
        return {"ind": ind, "st": self._contact_state}

    def _barrier_values(self) -> dict:
        return {"params": self._params, "stiffness": self.settings.barrier_stiffness,
                "j_hat": self.settings.barrier_det_f}

    def _deviatoric(self) -> DeviatoricTerm:
        """The deviatoric term's constant parts, made on first use. The term is quadratic in u:

            E_dev(u) = int mu/2 (|I + grad u|^2 - 3) = c . u + u . H_dev u / 2,   gradient  c + H_dev u,

        H_dev = int mu grad du : grad v (all dofs, the fixed ones too) and c = int mu I : grad v (the gradient at
        u = 0), both integrated at order 2 (exact for P2). One sparse product then gives the term's energy or gradient
        (``_energy``, ``_gradient``) instead of an integration at 4 points per tet."""
        if self._dev is None:
            vals = {"params": self._params}
            # with the mapped construction, as the other parts: every element's node pairs are blocks, none pruned
            # where it is zero (the default construction drops such blocks, e.g. on an axis-aligned mesh)
            H = fem.integrate(elasticity.deviatoric_hessian_form, quadrature=self._q_dev,
                              fields={"du": self._trial, "v": self._test}, values=vals, output_dtype=wp.float64,
                              bsr_options={"construction": "mapped", "capacity": "auto"})
            H.nnz_sync()
            with wp.ScopedDevice(self.device):
                c = fem.integrate(elasticity.deviatoric_gradient_form, quadrature=self._q_dev,
                                  fields={"u": self._space.make_field(), "v": self._test}, values=vals,
                                  output_dtype=wp.vec3d)
            self._dev = DeviatoricTerm(H, c, block_row_operator(H), wp.empty_like(c), block_keys(H))
        return self._dev

    def _tets(self) -> TetGeometry:
        """The tets as the tet-by-tet terms see them (volumetric_hessian.py, barrier_terms.py), made on first use."""
        if self._tet_geometry is None:
            self._tet_geometry = TetGeometry.of(self._space, self.vertices_mm, self.tets)
        return self._tet_geometry

    def _barrier_check_points(self) -> BarrierCheckPoints:
        """The barrier's tets and check points on the device (barrier_terms.py), made on first use."""
        if self._barrier_points is None:
            self._barrier_points = BarrierCheckPoints.make(self._tets(), self._q_det, self.device)
        return self._barrier_points

    def _energy(self, u, ind) -> float:
        """E(u) (N mm): each term added into one device scalar (``self._energy_sum``), read once; on a GPU the
        launches are replayed as a CUDA graph per displacement field, indenter struct and contact stiffness
        (replay.py)."""
        self._launch_energy(u, ind)
        return float(self._energy_sum.numpy()[0])

    def _launch_energy(self, u, ind) -> None:
        key = ("energy", u.dof_values.ptr, id(ind), float(ind.stiffness))
        self._graphs.run(key, (u, ind), lambda: self._energy_terms(u, ind))

    def _energy_and_min_det(self, u, ind, prepare: tuple[tuple, Callable[[], None]] | None = None
                            ) -> tuple[float, float | None]:
        """(E(u), the smallest det F at u) for the line search's trial u: on a GPU both are launched and read together
        (E copied next to the det F's extremes, one read), so that the host waits once (most trials are taken, and the
        det F then decides); on the CPU, where a read costs no wait, the det F is None (``_min_det`` where it is
        needed). ``prepare``: (what it adds to the graph's key, launches) that make u, run first in the same graph
        (trial_point.py: the trial point; GPU only)."""
        if not self.device.is_cuda:
            return self._energy(u, ind), None
        out = self._det_work[1]

        def launches() -> None:  # one graph per field, indenter struct and contact stiffness (replay.py)
            if prepare is not None:
                prepare[1]()
            self._energy_terms(u, ind)
            self._min_det_terms(u)
            wp.copy(out, self._energy_sum, dest_offset=3, count=1)  # over a partial that the combine has used

        key = ("trial", u.dof_values.ptr, id(ind), float(ind.stiffness), *(prepare[0] if prepare is not None else ()))
        self._graphs.run(key, (u, ind), launches)
        (low, _), energy = read_extremes(out, also=1)
        return energy[0], low

    def _energy_terms(self, u, ind) -> None:
        """E(u)'s terms summed into ``self._energy_sum`` (launches only)."""
        vals = {"params": self._params}
        dev = self._deviatoric()
        total = self._energy_sum
        total.zero_()
        dev.product.matvec(u.dof_values, dev.c, dev.work, 0.5, 1.0)  # H_dev u / 2 + c: E_dev = u . that
        add_dot(u.dof_values, dev.work, total)
        fem.integrate(elasticity.volumetric_energy_form, quadrature=self._q_vol, fields={"u": u}, values=vals,
                      output=total, add=True)
        if self.settings.barrier_det_f > 0.0:
            fem.integrate(elasticity.barrier_energy_form, quadrature=self._q_det, fields={"u": u},
                          values=self._barrier_values(), output=total, add=True)
        if ind.count:
            fem.integrate(contact.contact_energy_form, quadrature=self._q_contact, fields=self._contact_fields(u),
                          values=self._contact_values(ind), output=total, add=True)

    def _gradient(self, ind, take_trial: bool = False) -> wp.array:
        """Gradient at self.u (N, vec3d per node), written into the kept ``self._g`` (the next call overwrites it);
        with ``take_trial``, self.u = the line search's trial ``self._u_try`` first (newton.py: the accepted step,
        copied in the gradient's graph instead of a launch of its own);
        also stores there the contact state and the barrier's energy, which ``_hessian`` uses (hessian_assembly.py;
        ``_barrier_acts``). The terms are added in the order of the energy (elastic, barrier, contact). On a GPU the
        launches are replayed as one CUDA graph per displacement field, indenter struct and contact stiffness
        (replay.py): the elastic terms with the barrier's energy summed alongside, the barrier's gradient (added only in
        the tets where some det F is below j_hat, found on the device; barrier_terms.py), then the contact state and
        gradient; nothing is read (the caller may read the barrier's energy with its own read, ``barrier_energy_read``).
        On the CPU, where a read costs no wait, the energy is read first and the barrier's gradient launched only where
        it is not 0 (the usual case)."""
        u = self.u
        if self.device.is_cuda:
            def launches() -> None:
                if take_trial:
                    wp.copy(u.dof_values, self._u_try.dof_values)
                self._gradient_terms(ind, barrier=self.settings.barrier_det_f > 0.0)

            self._graphs.run(("gradient", u.dof_values.ptr, id(ind), float(ind.stiffness), take_trial), (u, ind),
                             launches)
            self._barrier_energy = None
        else:
            if take_trial:
                wp.copy(u.dof_values, self._u_try.dof_values)
            self._elastic_gradient_terms()
            self._barrier_energy = None
            self._gradient_terms(ind, barrier=self._barrier_acts, elastic=False)
        self._contact_stale = None
        return self._g

    def _gradient_terms(self, ind, barrier: bool, elastic: bool = True) -> None:
        """The gradient's terms into ``self._g`` (launches only): the elastic ones (unless ``elastic`` is False: the
        caller launched them), the barrier's where ``barrier``, the contact's where an indenter is given."""
        if elastic:
            self._elastic_gradient_terms()
        if barrier:
            s = self.settings
            self._barrier_check_points().add_gradient_to(self._g, self.u.dof_values, self._params, s.barrier_stiffness,
                                                         s.barrier_det_f)
        if ind.count:
            self._contact_gradient_terms(ind)

    @property
    def _barrier_acts(self) -> bool:
        """Whether some det F is below the barrier's threshold at the last ``_gradient``'s u (its energy is not 0;
        otherwise its gradient and Hessian are 0): the energy read now unless the caller has read it with its own
        read since (``barrier_energy_read``)."""
        if not self.settings.barrier_det_f > 0.0:
            return False
        if self._barrier_energy is None:
            self._barrier_energy = float(self._barrier_sum.numpy()[0])
        return self._barrier_energy > 0.0

    def barrier_energy_read(self, energy: float) -> None:
        """The barrier's energy at the last ``_gradient``'s u (N mm), read by the caller with its own read (newton.py:
        with the gradient's norm), so that ``_barrier_acts`` reads nothing."""
        self._barrier_energy = energy

    def contact_stale_read(self, flag: float) -> None:
        """The contact side subset's coverage flag (contact_sides.py ``launch_coverage``) at the last ``_gradient``'s
        u, read by the caller with its own read: 0 lets ``_contact_subset`` (hessian_assembly.py) keep the subset
        without reading the contact state. Only on a GPU, where ``_gradient`` launches it."""
        self._contact_stale = flag > 0.0

    def _elastic_gradient_terms(self) -> None:
        """The deviatoric and volumetric gradient into ``self._g``, the barrier's energy into ``self._barrier_sum``
        (launches only)."""
        dev = self._deviatoric()
        dev.product.matvec(self.u.dof_values, dev.c, self._g, 1.0, 1.0)  # H_dev u + c
        fem.integrate(elasticity.volumetric_gradient_form, quadrature=self._q_vol, fields={"u": self.u, "v": self._test},
                      values={"params": self._params}, output=self._g, add=True)
        if self.settings.barrier_det_f > 0.0:
            self._barrier_sum.zero_()
            fem.integrate(elasticity.barrier_energy_form, quadrature=self._q_det, fields={"u": self.u},
                          values=self._barrier_values(), output=self._barrier_sum, add=True)

    def _contact_gradient_terms(self, ind) -> None:
        """The contact state at self.u and the contact gradient added into ``self._g`` (launches only)."""
        fem.interpolate(contact.state_form, at=self._q_contact, fields=self._contact_fields(self.u),
                        values=self._contact_values(ind))
        fem.integrate(contact.contact_gradient_form, quadrature=self._q_contact, fields={"v": self._side_test},
                      values={"st": self._contact_state}, output=self._g, add=True)
        if self.device.is_cuda:  # whether the contact Hessian's side subset still holds, for the caller's read
            st = self._contact_state
            self._contact_sides.launch_coverage(st.k_normal, st.k_slip, st.k_slip_dir, ind.count,
                                                self._q_contact.total_point_count())

    def _launch_free_norm(self, g: wp.array) -> None:
        """|g| over the free components (N) of ``g`` (a gradient: vec3d per node) into kept buffers, for
        ``_read_free_norm``; replayed as a CUDA graph per g on a GPU (replay.py)."""
        rhs, out = self._free_norm_work
        if g.shape != rhs.shape:
            raise ValueError(f"a gradient of {g.shape[0]} nodes for a mesh of {rhs.shape[0]}")
        self._graphs.run(("free_norm", g.ptr), (g,),
                         lambda: launch_negated_free_and_load(g, self._fixed_mask, rhs, out))

    def _read_free_norm(self) -> float:
        """The last ``_launch_free_norm``'s |g| (N), in one read."""
        return read_negated_free(*self._free_norm_work, 2)[1]

    def _free_norm(self, g: wp.array) -> float:
        """``_launch_free_norm`` and its read."""
        self._launch_free_norm(g)
        return self._read_free_norm()

    def _launch_min_det(self, u) -> None:
        """The smallest det F at the barrier's check points (4 per tet) into kept buffers, for ``_read_min_det``;
        replayed as a CUDA graph per displacement field on a GPU (replay.py)."""
        self._graphs.run(("min_det", u.dof_values.ptr), (u,), lambda: self._min_det_terms(u))

    def _read_min_det(self) -> float:
        """The last ``_launch_min_det``'s smallest det F (NaN where any is NaN), in one read."""
        return read_extremes(self._det_work[1])[0]

    def _min_det(self, u) -> float:
        """``_launch_min_det`` and its read."""
        self._launch_min_det(u)
        return self._read_min_det()

    def _min_det_terms(self, u) -> None:
        """det F at the barrier's check points and their extremes into ``self._det_work`` (launches only)."""
        J, out = self._det_work
        fem.interpolate(elasticity.det_form, dest=J, at=self._q_det, fields={"u": u})
        launch_extremes(J, out)
