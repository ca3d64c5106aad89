"""Newton for one quasi-static (sub)step, as a mixin of ``QuasiStaticSolver`` (solver.py).

Where the iterations of the earlier solver went (tiny press fixture, friction 0.5: 19-23 per frame) and what
replaced each source (scripts/fem_frame_timing.py, BENCHMARKS.md ``fem_newton_iterations_cpu``):

- Friction's lag (normal pressure and tangent plane at u_lag) was an outer loop: Newton to convergence, move
  the lag, Newton again (5 Newton solves per step, each ending with an assembly and solve that only
  confirmed convergence). Here the lag is moved inside Newton as soon as Newton is closer to the current
  lag's solution than the lag is to u (``_move_lag``): an inexact fixed point on the lag.
- Convergence needed a full Newton step below ``newton_tol_mm``, i.e. one more Hessian assembly and solve
  after the last real step. After a full step (alpha = 1) the next step is now estimated from the new
  gradient with the last Hessian (``LinearSolver.solve_last``: CG preconditioned with the kept factorisation).
- Each (sub)step started from the last state. It now starts from the last increment scaled to this step's
  pose increment when that lowers E and keeps det F > 0 (warm_start.py ``_warm_start``); on a slide its contact also
  gives friction's first lag.
- The contact stiffness raise re-solved the whole step; it now happens at convergence inside Newton and
  Newton goes on from there (``_raise_stiffness``).
- The line search accepted steps that invert an element and the step then failed after the fact (and was
  sub-stepped); it now rejects them (det F <= 0 at any quadrature point of ``_min_det``).

Issue 12, second pass (scripts/fem_frame_timing.py; scripts/fem_stability.py's slide cases):

- Friction's stick-slip switch was the main cost: without friction the same frames take 5-7 iterations.
  ``SolverSettings.slip_eps_mm`` is 0.05 mm instead of 0.01 mm (see there).
- The volumetric Hessian's geometric term was always clamped (elasticity.py), which makes the Hessian inexact
  wherever the clamp acts and the end of Newton linear instead of quadratic (seen on the slides: steps
  shrinking 4x per iteration). The exact Hessian is tried first and the clamped one only where CHOLMOD finds
  the exact one is not positive definite (``_hessian_ladder``).
- The line search halved the step; it now jumps to the minimiser of the parabola through E(0), E'(0) and
  E(alpha) (within [0.1, 0.5] alpha, Nocedal & Wright 3.5), which lands nearer the minimum along the Newton
  direction when friction makes the full step overshoot.
- Where a slide starts the last increment points the wrong way (down); the warm start also tries u_prev
  carried along by the indenter's tangential translation (warm_start.py ``_carried``): the dent starts where it will
  be.

Issue 12, third pass, the device path (scripts/fem_phase_profile.py; BENCHMARKS.md ``fem_newton_variants_gpu``):
CG was 80 % of a press-and-slide frame on an H100, 500 iterations per Newton system at its 1e-8 tolerance.
Newton's systems are now solved inexactly (``FORCING_MAX``; tightened to ``LinearSolver.cg_tol``, linear.py, once
the step is small enough to decide convergence), and the step estimate and early lag moves that the host path had
(``solve_last``) use the last device system: 25 CG iterations per solve instead of 500, 1.4x faster frames.

Issue 12, fourth pass (BENCHMARKS.md ``fem_definite_cg_gpu``): the device path took the clamped Hessian always,
because Warp's CG cannot tell an indefinite matrix before its iteration cap; where the clamp acts (in compression,
almost everywhere) Newton then converges linearly. The device CG now stops at its first direction of non-positive
curvature (definite_cg.py), so the device tries the exact Hessian first as the host path does, and solves its
systems to a tighter forcing term (``FORCING_MAX`` 0.01: an exact-Hessian step solved to 0.1 wastes the Hessian's
accuracy): press_slide frames 1-5 in 82 Newton iterations instead of 111, 1.26x faster on an H100.

Issue 12, fifth pass, the host path (BENCHMARKS.md ``fem_host_inexact_newton_cpu``): the host solved every Newton system
to a relative residual of 1e-6, factorising anew wherever the kept factorisation's PCG could not get there. It now solves
to the forcing term as the device does (linear.py), from the step estimate where there is one, and no step is estimated
right after a lag move (on the tiny press fixture such an estimate never showed convergence: the move shifts the
solution). Tiny press fixture, frames 0-1 on the 2-core CPU: 8 -> 4 factorisations, 18 -> 14 Newton iterations,
4.9-5.2 -> 3.8-4.0 s. On an H100 (the estimate skip is the only device-path change) train_random sequences 0-7 took
1193 against 1233 Newton iterations (``fem_lag_estimate_gpu``).

Issue 12, sixth pass, the device path again (press_slide frames 1-9 on an H100: 0.88-0.98x, 0.89-0.93x and 0.95x the
time in three steps, each against the tree before it in one lease; about 0.33 s per frame at the end): the gradient, step
and step estimate stay on the device and are reduced there to the scalars this loop reads (reductions.py;
``fem_device_reductions_gpu``); the step estimate is solved to a loose tolerance within a larger cap instead of running
into its cap and being thrown away, with friction's lag then moved at a closer remaining step (friction_lag.py
``LAG_MOVE_RATIOS``; ``fem_step_estimate``); the line search's energy and det F replay CUDA graphs (replay.py;
``fem_graph_replay_gpu``), and so do the gradient and Hessian assembly (0.90-0.93x on an H200,
``fem_gradient_hessian_replay_gpu``).

Issue 12, seventh pass (contact_prediction.py; BENCHMARKS.md ``fem_contact_prediction_gpu``): on a release the gel
springs back into the lifting indenter, and the full Newton steps, which see the contact only where it is at u, went
into the indenter and were cut back by the line search (press_slide's release frame: 24-29 Newton iterations). On
steps that lift an indenter, a refused full step is now solved again with the contact it predicts (a primal-dual active
set step on the penalty term): the release frame takes 12-13, press_slide's median per frame falls from 15.5 to 12.5-13,
and its time per frame is unchanged within the runs' spread on an H100.

Issue 12, eighth pass (BENCHMARKS.md ``fem_folded_reads_gpu``): the GPU was busy for 62 % of press_slide's frames, the
host reading a device scalar 13 times per Newton iteration, each read draining the GPU. A pass now reads the gradient's
norm with the barrier's energy, friction's lag distance and, on a GPU, the contact side subset's coverage and E where
the line search needs it (``_read_gradient``); a device step's slope and length, and a step estimate's length, come
with the CG's state (``LinearSolver.known_summary``): 6.4 reads per Newton iteration, frames 0.74-0.87x the time on an
H100 (about 0.13-0.16 s), the Newton iterations within the runs' spread.

Issue 12, ninth pass (scripts/fem_gpu_gaps.py; BENCHMARKS.md ``fem_host_operations_gpu``): the GPU still waited for the
host about a fifth of each frame, spread over many host operations of 60-150 us each. The gradient's reductions and
what is read with them are replayed as one graph into kept buffers (``_read_gradient``), a trial point is one launch
(``_set_trial``), a solve's set-up, friction's lag update, the largest penetration and the frame's wrench are graphs
too (device_linear.py, contact_records.py), the gradient is one graph and the line-search trial another (assembly.py),
a solve's limits are copied in by the CG's graph from pinned memory (definite_cg.py), and solutions go into kept arrays
(device_linear.py ``SOLUTIONS``): press_slide frames 1-9 0.91-0.94x the time with the gradient read, the trial point,
a solve's set-up and the wrench changed (one lease, 0.103-0.107 s per frame), 0.71-0.89x with the contact records too
(a slower lease), then a median of about 0.96x with the rest (0.100-0.110 s per frame, a median of 0.105 s).

Issue 12, tenth pass (BENCHMARKS.md ``fem_launches_folded_gpu``): the device CG's graph takes a solve's right-hand side
and sets x = 0 itself (definite_cg.py ``fixed``), the accepted trial is copied into u by the next gradient's graph
(``take_trial``), the trial point is launched in the trial's graph, reading du's row among the kept solutions and alpha
at each replay (trial_point.py ``_try_step``), and a frame's records are launched together, then read (solver.py): 2.0
instead of 4.6 one-by-one launches per Newton iteration, 5 % less host time outside the reads, the frames within their
spread (a median of 0.107 s, as the tree before alternated with them).

Issue 12, eleventh pass (BENCHMARKS.md ``fem_force_forcing_gpu``): where the scenes' force test ends Newton, the last
systems of a load step were solved to relative residuals of 1e-3 to 1e-4 (the forcing term |g| / |g_first|, and the
refinement to ``cg_tol`` for the step-length test) at a force left of only a few times the test's bound, which a step
solved to a residual of half the bound already meets. Each system is now solved no tighter than the force test needs
(convergence_tests.py ``_force_forcing``): press_slide's Newton systems 0.65x the CG iterations, frames 1-9 0.85x
the time (14 alternated pairs on an H100, a median of 0.092 s per frame), 122-132 Newton iterations against 122-126,
the markers as close to a lag-converged, step-length-tested reference as before.

Issue 12, twelfth pass (BENCHMARKS.md ``fem_no_progress_gpu``): next to elements flattened towards det F = 0 Newton
could creep along the inversion barrier for its whole iteration cap, |g| growing by orders of magnitude, without the 10
short line searches in a row that give a step up. A (sub)step that can still be halved is now also given up after 30
steps since its lowest |g| (convergence_tests.py ``StallWatch``): on train_random over 120 sequences (an H100) 1
step reached the cap against 6, the slowest frame 8.0-11.0 s of physics against 14.9-27.2 s.
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
