"""Newton for one quasi-static (sub)step, as a mixin of ``QuasiStaticSolver`` (solver.py).

E(u), the gel's elastic energy with the inversion barrier, the penalty contact and friction with its normal pressure and
tangent plane lagged (assembly.py, contact.py), is minimised over the free displacement dofs (mm) for the indenters'
poses of the (sub)step. Each Newton iteration takes the exact Hessian, or the clamped or Gauss-Newton one where it is
not positive definite or gives no descent step (``_hessian_ladder``), solves its system inexactly (``FORCING_MAX``,
``EXACT_BELOW``) and backtracks along the step (Armijo on E, a quadratic-interpolation cut) without ever accepting det F
<= 0. Inside the loop friction's lag moves (friction_lag.py), the contact stiffness rises at convergence
(``_raise_stiffness``), and on releases a refused full step is solved again with the contact it predicts
(contact_prediction.py); it starts from the warm start (warm_start.py) and ends by the convergence tests, or gives the
step up: at the iteration cap or where it creeps (convergence_tests.py), where the line search fails or no Hessian gives
a descent direction (``_newton``, which says how the pieces fit together).

What each part replaced, and the measurements behind it (issue 12's twelve passes): docs/fem_newton_history.md.
"""

from __future__ import annotations

import numpy as np
import warp as wp
import warp.fem as fem
from scipy.spatial.transform import Rotation

from transtac_sim.physics.convergence_tests import ConvergenceTests, StallWatch
from transtac_sim.physics.elasticity import CLAMPED, EXACT
from transtac_sim.physics.friction_lag import FrictionLag
from transtac_sim.physics.reductions import (
    launch_negated_free_and_load,
    max_abs,
    read_negated_free,
    step_summary,
)
from transtac_sim.physics.trial_point import TrialPoints
from transtac_sim.physics.warm_start import lifts_off

#: Inexact Newton (Eisenstat & Walker 1996): the CG (device; on the host, preconditioned with the kept factorisation,
#: linear.py) solves each Newton system to a relative residual
#: of min(FORCING_MAX, |g| / |g_first|), |g_first| the gradient at the (sub)step's first pass: loose while
#: far from the solution, where an exact Newton step is wasted, and tightening in proportion to |g| (which
#: keeps Newton's convergence quadratic), but no tighter than the force test needs where a scene has it
#: (convergence_tests.py ``_force_forcing``). scripts/bench_linear_solvers.py: CG iterations against tolerance.
#: 0.01 rather than 0.1 since the device takes the exact Hessian where it is positive definite: on press_slide
#: frames 1-5 (H100, scripts/fem_phase_profile.py --forcing-max) 82 Newton iterations and 7.6-7.9 s against 103-105
#: and 9.2-9.3 s with 0.1, the same CG iterations in all.
FORCING_MAX = 0.01

#: a Newton system's CG goes on to the tight tolerance (linear.py ``cg_tol``; the force test's floor where that is
#: higher, convergence_tests.py ``_force_forcing``) where its step is below this many newton_tol_mm: there the step's
#: length decides the convergence test, and a loosely solved step is shorter
#: (10 took 13 % more Newton iterations on press_slide, BENCHMARKS.md ``fem_slide_iterations_gpu``)
EXACT_BELOW = 100.0


class NewtonSteps(ConvergenceTests, FrictionLag, TrialPoints):
    """Newton's method for ``QuasiStaticSolver`` (which provides the fields, assembly and linear solver); when
    friction's lag moves inside it: friction_lag.py."""

    def _newton(self, ind, may_stall: bool = False, lifting: bool = False) -> tuple[bool, int, str, float]:
        """Minimises E over u, from self.u, for one (sub)step: (converged, Newton iterations, why not, the
        largest penetration (mm) at the solution). With ``may_stall`` (the step can still be halved) it gives up where
        Newton creeps instead of converging (convergence_tests.py ``StallWatch``: line searches cut short in a row,
        or no new lowest |g| for many steps). With ``lifting`` (the step lifts an indenter off the gel), a full step
        refused by its energy is solved again with the contact it predicts (contact_prediction.py) and that full step
        is tried.

        Each pass: gradient at u (with friction's current lag), the estimated remaining Newton step, then a lag move
        (``_move_lag``), the convergence test, or a Newton iteration: Hessian, step, line search. Converged when the
        Newton step is below ``newton_tol_mm`` and |g| is at most ``max_residual_n`` (``_short_step_converges``), or
        with ``newton_force_rtol`` where |g| is at most that fraction of the support's normal load
        (``_force_balanced``), and friction's lag is within 10 newton_tol_mm of u (or was moved ``friction_lag_moves``
        times): after a full step (alpha = 1) that step is estimated from the new gradient with the last Hessian
        (``LinearSolver.solve_last``: no assembly, no factorisation, refined to the tight tolerance only where its
        length is near the threshold it is compared with, ``_estimate_band``; not after a lag move made on an estimate,
        where the step is seldom converged, nor where the force test holds: there Newton has converged or the lag moves
        whatever the estimate says), otherwise it is the full Newton step itself; the estimate also starts the next
        system's solve on the host. The linear solver solves each system to the forcing tolerance
        (``FORCING_MAX``), and to its tight one where the step is within ``EXACT_BELOW`` newton_tol_mm, but no tighter
        than the force test needs where it is on (convergence_tests.py ``_force_forcing``; a step solved looser than
        the tight tolerance does not end Newton by its length). At convergence a
        penetration above ``penetration_tol_mm`` raises the contact stiffness (``_raise_stiffness``) and Newton goes on
        from there. The Armijo back-tracking line search on E (quadratic interpolation) never accepts a step that makes
        any det F <= 0. Iterations count Newton steps (each assembles the exact Hessian and, where that is not positive
        definite, the clamped or Gauss-Newton one)."""
        s = self.settings
        tol = s.newton_tol_mm
        friction = any(i.friction > 0 for i in self.indenters)
        iterations, raises, lags, full_step, inverted = 0, 0, 0, False, False
        watch = StallWatch(s.newton_no_progress_steps)  # whether Newton creeps (``may_stall``)
        step_max = np.inf  # max |du| (mm) of the last Newton step
        g_first = None  # |g| at the first pass: the forcing term's reference
        energy_here = None  # E at self.u where the line search has just evaluated it (the same u, lag and stiffness)
        take_trial = False  # the line search's accepted trial is still to be copied into u (by the next gradient)
        floored = True  # systems solved no tighter than the force test needs (``_force_forcing``) until a line search
        # fails on such a step
        while True:
            lag_open = friction and lags < s.friction_lag_moves
            rhs, g_norm, load, lag_change, energy_at_u = self._read_gradient(ind, full_step and lag_open,
                                                                             energy_here is None, take_trial)
            take_trial = False
            energy_here = energy_here if energy_at_u is None else energy_at_u
            if g_norm == 0.0:  # e.g. nothing touches yet: already at equilibrium
                return True, iterations, "", 0.0
            g_first = g_first or g_norm
            watch.gradient(g_norm)
            # where the force test holds, Newton has converged or friction's lag moves whatever a step estimate says
            balanced = self._force_balanced(g_norm, load)
            change = lag_change if not balanced else None
            estimate = self._linear.solve_last(rhs, **self._estimate_band(change)) if full_step and not balanced \
                else None
            known = self._linear.known_summary(estimate) if estimate is not None else None
            remaining = np.inf if estimate is None else known[1] if known else max_abs(estimate)
            if lag_open and self._move_lag(ind, remaining, change):
                lags, energy_here, full_step = lags + 1, None, False
                watch.restart()
                continue
            # converged on the force left (no estimate was made) once friction's lag is settled, or on the estimated
            # step, which is taken too (below tol E changes by round-off)
            if balanced or (remaining < tol and self._short_step_converges(g_norm)):
                if balanced and lag_open and self._move_lag(ind, 0.0):
                    lags, energy_here, full_step = lags + 1, None, False
                    watch.restart()
                    continue
                energy_here = None
                if estimate is not None:
                    self._set_trial(estimate, 1.0)
                    if self._min_det(self._u_try) > 0.0:
                        wp.copy(self.u.dof_values, self._u_try.dof_values)
                pen = self._raise_stiffness(ind, raises)
                if pen is not None:
                    return True, iterations, "", pen
                raises, full_step = raises + 1, False
                watch.restart()
                continue
            if iterations == self._newton_iteration_cap():
                why = " (line-search steps cut short by inverted elements, det F <= 0)" if inverted else ""
                if min(remaining, step_max) < tol and not self._short_step_converges(g_norm) \
                        and not self._linear.last_shift:
                    why += (f" (its steps below newton_tol_mm at |gradient| {g_norm:.3g} N above max_residual_n = "
                            f"{s.max_residual_n:g} N, smallest det F {self._min_det(self.u):.3g})")
                return False, iterations, "Newton iteration limit reached" + why, 0.0
            iterations += 1
            energy = energy_here if energy_here is not None else self._energy(self.u, ind)
            # solved no tighter than the force test needs; a step solved looser than cg_tol tests nothing by its length
            tight = max(self._linear.cg_tol, self._force_forcing(g_norm, load) if floored else 0.0)
            tested = tight <= self._linear.cg_tol
            rtol = max(min(FORCING_MAX, g_norm / g_first), tight)
            ladder = self._hessian_ladder()
            for rung, (geometric, clamp) in enumerate(ladder):  # all but the last must be positive definite
                # near convergence (the step below EXACT_BELOW tol) the step's length decides the convergence test
                H = self._hessian(ind, geometric, clamp)
                du = self._linear.solve(H, rhs, definite=rung < len(ladder) - 1, rtol=rtol,
                                        exact_below=EXACT_BELOW * tol, guess=estimate, tight=tight)
                if du is None:  # this Hessian is not positive definite here
                    self.stats["indefinite_hessians"] += 1
                    continue
                du_dot_rhs, step_max, finite = self._linear.known_summary(du) or step_summary(du, rhs)
                slope = -du_dot_rhs  # E'(0) along du: du . g
                if finite and ((step_max < tol and self._short_step_converges(g_norm)) or slope < 0.0):
                    break  # at a round-off gradient (e.g. GPU atomics where nothing touches) the slope means nothing
            else:
                return False, iterations, "Newton direction is not a descent direction", 0.0
            # a shifted step tests nothing, nor does a short one at a large |g| (``_short_step_converges``) or one
            # solved looser than cg_tol
            alpha = 1.0 if step_max >= tol or self._linear.last_shift or not tested \
                or not self._short_step_converges(g_norm) else 0.0
            may_predict = lifting and ind.count > 0 and alpha == 1.0 and not self._linear.last_shift
            newton_step = None  # (du, du . rhs, max |du|, its next alpha) while a predicted step is tried in its place
            while alpha > 1e-6:
                e_try, det_try = self._try_step(du, alpha, ind)
                if np.isfinite(e_try) and e_try <= energy + 1e-4 * alpha * slope + 1e-12 * abs(energy):
                    if (det_try if det_try is not None else self._min_det(self._u_try)) > 0.0:
                        break
                    inverted = True
                    cut = 0.5
                elif np.isfinite(e_try) and e_try > energy + slope * alpha:
                    # the minimiser of the parabola through E(0), E'(0) and E(alpha), kept within [0.1, 0.5] alpha
                    cut = float(np.clip(-0.5 * slope * alpha / (e_try - energy - slope * alpha), 0.1, 0.5))
                else:
                    cut = 0.5
                self.stats["backtracks"] += 1
                # a full step refused by its energy (not by NaN, i.e. inverted elements) is solved again with the
                # contact it predicts, if any (contact_prediction.py), and that full step is tried; where it is refused
                # too, the line search goes on along the Newton step
                predicted = (self._predict_contact(ind, H, rhs, du, rtol, EXACT_BELOW * tol, tight)
                             if may_predict and np.isfinite(e_try) else None)
                may_predict = False
                if predicted is not None:
                    newton_step = (du, du_dot_rhs, step_max, alpha * cut)
                    du, du_dot_rhs, step_max = predicted
                elif newton_step is not None:
                    du, du_dot_rhs, step_max, alpha = newton_step
                    newton_step = None
                else:
                    alpha *= cut
                slope = -du_dot_rhs
            else:  # converged (a full step below the tolerance) or, below 100 x tol, E differs by round-off only (not
                # where |g| is above max_residual_n: there a failed line search fails the step)
                energy_here = None
                self._set_trial(du, 1.0)
                if (step_max >= 100.0 * tol or not self._short_step_converges(g_norm)
                        or not self._min_det(self._u_try) > 0.0):
                    why = "line search failed" + (" (every step tried made an inverted element, det F <= 0)"
                                                  if inverted else "")
                    return False, iterations, why, 0.0
                if not tested:  # solved looser than cg_tol, its length shows nothing: the rest of the (sub)step's
                    # systems to cg_tol
                    floored = False
                    continue
                wp.copy(self.u.dof_values, self._u_try.dof_values)
                if friction and lags < s.friction_lag_moves and self._move_lag(ind, 0.0):
                    lags, full_step = lags + 1, True
                    watch.restart()
                    continue
                pen = self._raise_stiffness(ind, raises)
                if pen is not None:
                    return True, iterations, "", pen
                raises, full_step = raises + 1, False
                watch.restart()
                continue
            full_step, energy_here, take_trial = alpha == 1.0, e_try, True  # u = u_try with the next gradient
            stalled = watch.step(alpha)
            if may_stall and stalled:
                wp.copy(self.u.dof_values, self._u_try.dof_values)
                return False, iterations, stalled, 0.0

    def _read_gradient(self, ind, lag_change: bool, energy: bool, take_trial: bool = False) -> tuple:
        """(-g and |g| on the free components, the normal load on the support, |u - u_lag| where ``lag_change``, E(u)
        where ``energy`` on a GPU) at self.u (set to the line search's trial first where ``take_trial``, in the
        gradient's graph: ``_gradient``), in one read (None for what is not asked for): the barrier's energy (for
        the Hessian, ``_barrier_acts``), on a GPU whether the contact Hessian's side subset still holds
        (``_contact_subset``), friction's lag distance (``_lag_change``) and E (for the line search, which would read it
        otherwise; on the CPU, where a read costs no wait, E is left to it: an E evaluated here is wasted where the pass
        moves the lag or converges) are reduced on the device and read with |g|. -g goes into the kept ``self._rhs``
        (the next call overwrites it), and the reductions and copies before the read are replayed as one CUDA graph
        on a GPU."""
        g = self._gradient(ind, take_trial)
        coverage = self.device.is_cuda and ind.count > 0  # the contact side subset's flag (``_gradient`` launched it)
        energy = energy and self.device.is_cuda
        if energy:
            self._launch_energy(self.u, ind)
        also = ((self._barrier_sum, 1),) + (((self._contact_sides.stale, 1),) if coverage else ()) \
            + (((self._energy_sum, 1),) if energy else ()) + (((self._lag_work, 2),) if lag_change else ())

        # one graph per combination of what is read (replay.py): every array it names is the solver's, made once
        def launches() -> None:
            if lag_change:
                self._launch_lag_change()
            launch_negated_free_and_load(g, self._fixed_mask, self._rhs, self._gradient_read, also)

        self._graphs.run(("gradient_read", coverage, energy, lag_change), (), launches)
        rhs, g_norm, load, barrier_energy, *more = read_negated_free(self._rhs, self._gradient_read,
                                                                     2 + sum(count for _, count in also))
        self.barrier_energy_read(barrier_energy)
        if coverage:
            self.contact_stale_read(more.pop(0))
        e = more.pop(0) if energy else None
        return rhs, g_norm, load, (float("nan") if more[1] else more[0]) if lag_change else None, e

    def _hessian_ladder(self) -> tuple[tuple[float, int], ...]:
        """(geometric, clamp) of the Hessians tried in turn for a Newton step: the exact one, the clamped one, then
        Gauss-Newton (elasticity.py ``EXACT``, ``CLAMPED``). A Hessian other than the last is passed over where the
        linear solver finds it is not positive definite: CHOLMOD on the host, the device CG at its first direction of
        non-positive curvature (definite_cg.py). The clamped one is not always: the device CG found it not positive
        definite on train_random sequences 9 (flat punch) and 17 (cube edge) on an H100 (cause not traced; in uniform
        compression with the barrier acting it is, tests/test_physics_barrier.py). The last is solved whatever it is: on
        the host by LU where CHOLMOD fails, on the device with a Levenberg-Marquardt shift where CG fails (device_linear.py)."""
        return ((1.0, EXACT), (1.0, CLAMPED), (0.0, CLAMPED))

    def _raise_stiffness(self, ind, raises: int) -> float | None:
        """At a converged state: its largest penetration (mm), or None after raising the contact stiffness.

        Penalty penetration is about p / k: above ``penetration_tol_mm``, k is raised by 1.5 x penetration /
        tolerance (at most 10x at a time, ``max_stiffness_raises`` times per step) and kept for the following
        frames; Newton goes on from the current state."""
        pen = self._max_penetration(ind)
        if pen <= self.settings.penetration_tol_mm or raises >= self.settings.max_stiffness_raises:
            return pen
        self.contact_stiffness *= min(10.0, 1.5 * pen / self.settings.penetration_tol_mm)
        ind.stiffness = self.contact_stiffness
        self._graphs.clear()  # their keys hold the old stiffness: none is replayed again
        self._linear.forget()
        self.stats["stiffness_raises"] += 1
        return None

    def _pose_step(self, prev_poses, poses) -> np.ndarray:
        """The indenters' pose increment as one vector (mm): translations, and rotation vectors times radius."""
        parts = []
        for ind, A, B in zip(self.indenters, prev_poses, poses, strict=True):
            turn = Rotation.from_matrix(B[:3, :3] @ A[:3, :3].T).as_rotvec() * ind.bounding_radius_mm
            parts += [B[:3, 3] - A[:3, 3], turn]
        return np.concatenate(parts)

    def _solve_step(self, poses, prev_poses, may_stall: bool = False) -> tuple[bool, int, str, float]:
        """One (sub)step from u_prev (converged at ``prev_poses``) to ``poses``; returns ``_newton``'s result
        (``may_stall``: see there)."""
        ind = self._indenter_struct(poses, prev_poses)  # the same struct every step: its graphs are replayed
        self._linear.new_load_step()
        wp.copy(self.u_lag.dof_values, self.u_prev.dof_values)
        # first lag: the contact of the last converged state, where it was (with the previous poses), or that of
        # the warm start if its contact is about as deep (on a slide it is where the contact has moved to)
        self._update_lag(self._indenter_struct(prev_poses, prev_poses, role="lag"))
        step = self._pose_step(prev_poses, poses)
        if self._warm_start(ind, step):
            wp.copy(self.u_lag.dof_values, self.u.dof_values)
            self._update_lag(ind)
        ok, iterations, why, pen = self._newton(ind, may_stall, lifts_off(step, self.settings.newton_tol_mm))
        self._last_ind = ind
        if ok:
            du = wp.clone(self.u.dof_values)
            fem.linalg.array_axpy(x=self.u_prev.dof_values, y=du, alpha=-1.0)
            self._increment = (du, step, pen)
        return ok, iterations, why, pen
