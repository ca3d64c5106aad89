"""Friction's lag inside Newton (newton.py), as a mixin of ``NewtonSteps``: when the lag moves, and which of Newton's
step estimates are refined to decide it.

Friction's normal pressure and tangent plane are taken at a lagged state u_lag (contact.py). Newton moves the lag to the
current u as soon as it is closer to this lag's solution than the lag is to u: its estimated remaining step (the step
estimate, ``LinearSolver.solve_last``) below r |u - u_lag|, r per linear solver (``LAG_MOVE_RATIOS``), and at most
``friction_lag_moves`` times per (sub)step: an inexact fixed point on the lag, each lag solved only as far as the next
one makes worth it (BENCHMARKS.md ``fem_friction_lag_moves``). The estimate is solved loosely and refined to the tight
tolerance only where its length is near the threshold it is compared with (``ESTIMATE_REFINE_BAND``).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from transtac_sim.physics.reductions import launch_max_abs, max_abs

#: friction's lag is moved once Newton's estimated remaining step is below this fraction of |u - u_lag| (``_move_lag``),
#: per linear solver: moved earlier (0.3, 1.0; with a second Hessian since removed) the press_slide frames took more
#: Newton iterations and their markers left the lag-converged solution by up to 0.45 mm (BENCHMARKS.md
#: ``fem_slide_iterations_gpu``). The device path ("cg") takes 0.03 since its step estimates converge
#: (device_linear.ESTIMATE_RTOL): with 0.1 its lag then moved earlier, and the 4 moves per step ended up to 0.012 mm
#: from the lag-converged markers on the tiny mesh with press_slide's motion, against 0.0016 mm with 0.03 and before;
#: the host path keeps 0.1 (0.03 there: the same markers, 20 instead of 16 Newton iterations on the tiny press fixture;
#: BENCHMARKS.md ``fem_step_estimate``)
LAG_MOVE_RATIOS = {"direct": 0.1, "cg": 0.03}

#: the step estimate (``LinearSolver.solve_last``) is solved loosely (device_linear.ESTIMATE_RTOL) and refined to the
#: tight tolerance only where its length (max |x|) is within these multiples of the threshold it is compared with, where
#: the comparison could go either way: friction's lag threshold (``_move_lag``) where the lag may still move, otherwise
#: newton_tol_mm (the convergence test); and, as before, never above ``ESTIMATE_REFINED_BELOW`` (``_estimate_band``).
#: Below the band the loose length decides as the refined one would: on press_slide (H100) the refined estimates were
#: 0.91-1.98 times as long as their loose ones (above ESTIMATE_REFINED_BELOW, where a lag threshold can lie, the loose
#: length decides as it always did). Before, every estimate below ESTIMATE_REFINED_BELOW was refined, which
#: took 3,625 of the estimates' 6,351 CG iterations; with the band 4-5 of 106-109 estimates are refined, the estimates
#: take 0.49-0.53x the CG iterations and the frames 0.88-0.95x the time, with the same Newton iterations and the markers
#: as close to the lag-converged ones as before (BENCHMARKS.md ``fem_estimate_refinement_gpu``). A loose estimate varies
#: from run to run with the device CG's round-off, and on a hard case (the stability table's flat punch rim) the state
#: then ends on another of the step's equilibria.
ESTIMATE_REFINE_BAND = (0.25, 2.0)
#: (multiples of newton_tol_mm) no estimate is refined above this length: the rule before the band
ESTIMATE_REFINED_BELOW = 10.0


class FrictionLag:
    """When friction's lag moves inside Newton (``NewtonSteps``, which provides the fields, the settings and the linear
    solver; contact_records.py ``_update_lag``)."""

    def _lag_change(self) -> float:
        """max |u - u_lag| (mm): how far friction's lag is from the current u."""
        return max_abs(self.u.dof_values, self.u_lag.dof_values)

    def _launch_lag_change(self) -> None:
        """``_lag_change`` without its read: [max |u - u_lag| over the entries without a NaN, count of entries with a
        NaN] into the kept ``self._lag_work`` (reductions.py ``launch_max_abs``), for the caller's read."""
        launch_max_abs(self.u.dof_values, self._lag_work, self.u_lag.dof_values)

    def _lag_threshold(self, change: float) -> float | None:
        """The remaining step (mm) below which friction's lag moves for a lag ``change`` (mm) away (``_move_lag``), or
        None where it does not move whatever the step (the change is below 10 newton_tol_mm)."""
        tol = self.settings.newton_tol_mm
        return None if change < 10.0 * tol else max(tol, LAG_MOVE_RATIOS[self._linear.method] * change)

    def _estimate_band(self, change: float | None) -> dict[str, float]:
        """``solve_last``'s band (mm) within which the step estimate is refined (``ESTIMATE_REFINE_BAND`` times the one
        threshold its length is compared with), below ``ESTIMATE_REFINED_BELOW`` newton_tol_mm. Where friction's lag
        may move (``change``: its distance from u, mm, >= 10 newton_tol_mm; None: it may not), that is the lag's
        threshold (``_move_lag``, at least newton_tol_mm): an estimate below it moves the lag before the convergence
        test is reached. Otherwise it is newton_tol_mm (the convergence test). An empty band refines nothing."""
        tol = self.settings.newton_tol_mm
        low, high = ESTIMATE_REFINE_BAND
        threshold = self._lag_threshold(change) if change is not None else None
        compared = threshold if threshold is not None else tol
        return {"refine_above": low * compared, "exact_below": min(ESTIMATE_REFINED_BELOW * tol, high * compared)}

    def _move_lag(self, ind, remaining: float, change: float | None = None) -> bool:
        """Moves friction's lag to the current u when Newton is closer to this lag's solution than the lag is to
        u: the estimated remaining step ``remaining`` (mm) is below max(newton_tol_mm, r x |u - u_lag|), r the linear
        solver's ``LAG_MOVE_RATIOS``, and |u - u_lag| >= 10 newton_tol_mm (``_lag_threshold``; ``change``: |u - u_lag|
        where the caller has it). True if moved (an inexact fixed point on the lag: each lag is solved only as far as
        the next one makes worth it, instead of to the tolerance)."""
        if remaining == np.inf:  # no step estimate: not closer than any change (no device read)
            return False
        threshold = self._lag_threshold(change if change is not None else self._lag_change())
        if threshold is None or remaining >= threshold:
            return False
        wp.copy(self.u_lag.dof_values, self.u.dof_values)
        self._update_lag(ind)
        self.stats["lag_updates"] += 1
        return True
