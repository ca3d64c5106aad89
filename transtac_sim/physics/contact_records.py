"""The contact's updates and measurements outside Newton's energy terms, as a mixin of ``QuasiStaticSolver`` (which
provides the quadratures, fields, contact state and indenter structs; assembly.py the gradient these use): friction's
lagged pressure and tangent plane (``_update_lag``) and the force imbalance the lag leaves
(``_launch_friction_lag_residual``), friction's stretch carried into the next step (``_keep_stick``), the largest
penetration (``_max_penetration``) and the indenters' wrench (``_launch_wrench``, ``_read_wrench``; the frame's records
are launched together and then read, load_stepping.py ``solve_frame``). On a GPU each is replayed as a CUDA graph per
field, indenter struct and contact stiffness (replay.py) into kept arrays: each warp.fem integration or interpolation
costs about half a millisecond of host work when launched on its own (press_slide on an H100: the frame's wrench was 6
integrations and 6 reads, now one graph and one read; BENCHMARKS.md ``fem_host_operations_gpu``).
"""

from __future__ import annotations

import numpy as np
import warp as wp
import warp.fem as fem

from transtac_sim.physics import contact
from transtac_sim.physics.reductions import launch_extremes, read_extremes


class ContactRecords:
    """Friction's lag, the stick memory, the largest penetration and the wrench for ``QuasiStaticSolver``."""

    def _update_lag(self, ind, u=None) -> None:
        """Friction's lagged normal pressure and tangent plane, from the field ``u`` (default u_lag); replayed as a CUDA
        graph per field, indenter struct and contact stiffness on a GPU (replay.py)."""
        if ind.count:
            field = self.u_lag if u is None else u
            self._graphs.run(("lag", field.dof_values.ptr, id(ind), float(ind.stiffness)), (field, ind),
                             lambda: fem.interpolate(contact.lag_form, at=self._q_contact,
                                                     fields={"u_lag": field.trace()}, values=self._contact_values(ind)))

    def _launch_friction_lag_residual(self, ind) -> bool:
        """|g| (N, on the free dofs) at self.u with friction's lagged pressure and tangent plane taken at u, launched
        into ``_free_norm``'s kept buffers for ``_read_free_norm`` (False: nothing launched, the residual is 0): the
        force imbalance that the lag leaves at a converged state. Small where the lag converged (Newton moves it only
        while it is 10 newton_tol_mm or more from u: 1e-6 to 1e-4 N in BENCHMARKS.md ``fem_friction_lag_residual``);
        larger where ``friction_lag_moves`` ran out first. 0 without friction. The lagged state is put back, and so are
        the gradient and the contact state (traction, stiffnesses) at u with it."""
        if not ind.count or not any(i.friction > 0 for i in self.indenters):
            return False
        st = self._contact_state
        kept = self._lag_kept
        wp.copy(kept[0], st.lag_g)
        wp.copy(kept[1], st.lag_n)
        self._update_lag(ind, self.u)
        self._launch_free_norm(self._gradient(ind))
        wp.copy(st.lag_g, kept[0])
        wp.copy(st.lag_n, kept[1])
        self._gradient(ind)
        return True

    def _keep_stick(self, ind) -> None:
        """Friction's stretch at the converged u, carried into the next step (contact.py ``stick_form``); left at 0
        without ``SolverSettings.friction_memory`` (each step's slip then starts from no traction)."""
        if ind.count and self.settings.friction_memory:
            self._graphs.run(("stick", self.u.dof_values.ptr, id(ind), float(ind.stiffness)), (self.u, ind),
                             lambda: fem.interpolate(contact.stick_form, at=self._q_contact,
                                                     fields=self._contact_fields(self.u),
                                                     values=self._contact_values(ind)))

    def _max_penetration(self, ind) -> float:
        """The largest penetration (mm) at the contact quadrature points; replayed as a CUDA graph per indenter struct
        and contact stiffness on a GPU (replay.py)."""
        if not ind.count:
            return 0.0
        pen, out = self._penetration_work

        def launches() -> None:
            fem.interpolate(contact.penetration_form, dest=pen, at=self._q_contact, fields={"u": self.u.trace()},
                            values={"ind": ind})
            launch_extremes(pen, out)

        self._graphs.run(("penetration", self.u.dof_values.ptr, id(ind), float(ind.stiffness)), (self.u, ind),
                         launches)
        return read_extremes(out)[1]

    def _launch_wrench(self, ind) -> None:
        """Each indenter's force (N) and torque about its reference point (N mm) at self.u, one integral per component
        into the kept ``self._wrench_work``, replayed as one CUDA graph on a GPU (replay.py), for ``_read_wrench``."""
        wrench = self._wrench_work

        def launches() -> None:
            for k in range(wrench.shape[0]):
                fem.integrate(contact.wrench_form, quadrature=self._q_contact, fields=self._contact_fields(self.u),
                              values=self._contact_values(ind) | {"which": k // 6, "component": k % 6},
                              output=wrench[k:k + 1])

        self._graphs.run(("wrench", self.u.dof_values.ptr, id(ind), float(ind.stiffness)), (self.u, ind), launches)

    def _read_wrench(self) -> np.ndarray:
        """The last ``_launch_wrench``'s wrench, (indenters, 6), in one read."""
        return self._wrench_work.numpy().reshape(len(self.indenters), 6).copy()  # on the CPU a view of the kept array
