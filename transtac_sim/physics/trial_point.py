"""The line search's trial points u + alpha du (newton.py), as a mixin of ``NewtonSteps`` (which provides the fields,
the assembly's energy and det F, and the linear solver): one launch each (``_set_trial``), or, on a GPU where du is one
of the device solver's kept solutions, launched inside the trial's graph, which reads du's row and alpha from pinned
memory at each replay (``_try_step``: one launch fewer per trial, one graph for every step and alpha; BENCHMARKS.md
``fem_launches_folded_gpu``).
"""

from __future__ import annotations

import warp as wp


@wp.kernel(enable_backward=False)
def _trial_point(u: wp.array(dtype=wp.vec3d), du: wp.array(dtype=wp.vec3d), alpha: wp.float64,
                 out: wp.array(dtype=wp.vec3d)):
    """out = u + alpha du (mm, per node): a line search's trial, written where a copy and an axpy took two launches."""
    i = wp.tid()
    out[i] = u[i] + alpha * du[i]


@wp.kernel(enable_backward=False)
def _kept_trial_point(u: wp.array(dtype=wp.vec3d), steps: wp.array2d(dtype=wp.vec3d),
                      step: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.vec3d)):
    """out = u + alpha du (mm, per node), du the row ``step[1]`` of ``steps`` and alpha ``step[0]``: the trial point
    of ``_try_step``'s graph, which reads whichever of the linear solver's kept solutions the host names at its
    replay."""
    i = wp.tid()
    out[i] = u[i] + step[0] * steps[int(step[1]), i]


class TrialPoints:
    """The line search's trial points for ``NewtonSteps``."""

    def _set_trial(self, du: wp.array, alpha: float) -> None:
        """u_try = u + alpha du, in one launch (``_trial_point``)."""
        wp.launch(_trial_point, dim=len(du), device=self.device,
                  inputs=[self.u.dof_values, du, wp.float64(alpha), self._u_try.dof_values])

    def _try_step(self, du: wp.array, alpha: float, ind) -> tuple[float, float | None]:
        """u_try = u + alpha du, and (E, the smallest det F) there (assembly.py ``_energy_and_min_det``; det F None on
        the CPU). On a GPU, where du is one of the linear solver's kept solutions (``LinearSolver.solution_row``: the
        device path's), the trial point is launched in the energy's graph, which reads alpha and du's row from pinned
        memory copied in at each replay (as definite_cg.py's limits): one graph for every step and alpha, one launch
        fewer per trial; otherwise ``_set_trial`` first."""
        kept = self._linear.solution_row(du) if self.device.is_cuda else None
        if kept is None:
            self._set_trial(du, alpha)
            return self._energy_and_min_det(self._u_try, ind)
        solutions, row = kept
        self._trial_host.numpy()[:] = (alpha, float(row))  # no replay still reads it: each ends in the trial's read

        def trial_point() -> None:
            wp.copy(self._trial_step, self._trial_host)
            wp.launch(_kept_trial_point, dim=solutions.shape[1], device=self.device,
                      inputs=[self.u.dof_values, solutions, self._trial_step, self._u_try.dof_values])

        return self._energy_and_min_det(self._u_try, ind, (("kept", solutions.ptr, self.u.dof_values.ptr), trial_point))
