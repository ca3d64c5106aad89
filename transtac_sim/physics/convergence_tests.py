"""Newton's convergence tests, as a mixin of ``NewtonSteps`` (newton.py): when a short step shows convergence, when the
force left does, how tightly a Newton system needs solving for the force test, and Newton's iteration cap.

Two tests end Newton (newton.py ``_newton``): the step-length test (the Newton step, or its estimate from the last
system, below ``newton_tol_mm``, at a force left of at most ``max_residual_n``: ``_short_step_converges``) and, where a
scene sets ``newton_force_rtol``, the force test (|g| at most that fraction of the normal load on the gel's support:
``_force_balanced``). Where the force test is on, each Newton system needs solving only until the linear model's force
after the step is within a fraction of the test's bound (``_force_forcing``, ``FORCE_FORCING``). Where a (sub)step can
still be halved, Newton gives it up once it creeps instead of converging (``StallWatch``).
"""

from __future__ import annotations

import numpy as np

#: Where Newton's force test is on (``_force_balanced``), a system is solved no tighter than this fraction of the
#: force test's bound over |g| (relative residual; ``_force_forcing``): the linear model's gradient after the step is
#: then within half the bound, and a tighter solve would only refine a state that the force test already accepts (not
#: oversolving the last steps, Eisenstat & Walker 1996). Each system is solved to
#: max(min(FORCING_MAX, |g| / |g_first|), cg_tol, this floor), its refinement (newton.py ``EXACT_BELOW``) to
#: max(cg_tol, floor). press_slide on an H100: Newton's systems 0.62-0.72x the CG iterations, frames 0.85x the time
#: (BENCHMARKS.md ``fem_force_forcing_gpu``); on the tiny mesh with press_slide's motion 0.5 took the fewest CG
#: iterations of 0.1, 0.25 and 0.5 at the same Newton iterations, and 1.0 took 9 % more Newton iterations
FORCE_FORCING = 0.5


#: A (sub)step that can still be halved gives up once this many Newton steps in a row were cut to STALL_ALPHA or less
#: by the line search: Newton is then creeping along the inversion barrier (elasticity.py) with the clamped Hessian, and
#: halves of the step converge far sooner. train_random sequence 0 (the cone) on an H100, frames 4 and 5: the whole
#: frame's step ran all 120 iterations (about 5 halvings each, 2,200 CG iterations per system, |g| rising from 6 to 35 N
#: while E fell) and failed, 16 of the frame's 17-22 s, before its halves converged in 12-81 iterations
#: (scripts/trace_sequence.py --newton; BENCHMARKS.md ``fem_newton_stall_gpu``).
STALL_STEPS = 10
STALL_ALPHA = 1.0 / 16.0


class StallWatch:
    """Whether Newton creeps instead of converging in one (sub)step (newton.py ``_newton``, which gives the step up
    where it can still be halved): ``STALL_STEPS`` line searches in a row cut to ``STALL_ALPHA`` or less, or
    ``no_progress_steps`` Newton steps taken since the pass with the lowest |g| of the (sub)step, the last of them
    before its |g| is read (``SolverSettings.newton_no_progress_steps``; 0: never). Both are counted afresh by
    ``restart`` (friction's lag moved or the contact stiffness raised: they change E and |g|)."""

    def __init__(self, no_progress_steps: int) -> None:
        self.no_progress_steps = no_progress_steps
        self.restart()

    def restart(self) -> None:
        self.short_steps, self.lowest, self.since_lowest = 0, np.inf, 0

    def gradient(self, g_norm: float) -> None:
        """A pass's |g| (N, free dofs)."""
        if g_norm < self.lowest:
            self.lowest, self.since_lowest = g_norm, 0

    def step(self, alpha: float) -> str:
        """A Newton step taken with line-search factor ``alpha``: why Newton creeps, or "" where it does not."""
        self.short_steps = self.short_steps + 1 if alpha <= STALL_ALPHA else 0
        self.since_lowest += 1
        if self.short_steps >= STALL_STEPS:
            return (f"Newton stalled: {STALL_STEPS} steps in a row cut to 1/{1 / STALL_ALPHA:g} or less by the line "
                    "search")
        if self.no_progress_steps and self.since_lowest >= self.no_progress_steps:
            return (f"Newton made no progress: {self.since_lowest} steps since the lowest |gradient| of the (sub)step "
                    f"({self.lowest:.3g} N)")
        return ""


class ConvergenceTests:
    """Newton's convergence tests for ``QuasiStaticSolver`` (which provides ``settings`` and the linear solver)."""

    def _short_step_converges(self, g_norm: float) -> bool:
        """Whether a Newton step below newton_tol_mm at a gradient of ``g_norm`` (N, free dofs) shows convergence: where
        |g| is at most ``max_residual_n``. Near a check point flattened towards J = 0 the inversion barrier
        (elasticity.py) costs little energy, but its force grows as j_hat^2 / J and its curvature as j_hat^2 / J^2, so
        Newton's step there is about J long whatever the force. On train_random (120 sequences, 8 MPS workers, an H100)
        7 whole-frame steps passed the step-length test at |g| of 4 to 1.4e4 N (steps down to 3.5e-9 mm) and were then
        refused by the solver's residual check; in a later run with this test (an H200), where a step below
        newton_tol_mm came at |g| above 100 N, min det F was at most 7.7e-6 (BENCHMARKS.md ``fem_short_step_gpu``).
        At such a |g| Newton goes on with full steps (J about doubled per step in that run), a short step must be a
        descent direction, and a line search that fails fails the step (before, a step below 100 newton_tol_mm whose
        line search failed was taken as converged, E differing by round-off only)."""
        return g_norm <= self.settings.max_residual_n

    def _force_balanced(self, g_norm: float, load: float) -> bool:
        """Whether |g| (``g_norm``, N) is at most ``newton_force_rtol`` times the normal ``load`` on the support (N; and
        at most ``max_residual_n``): False where that setting is None or 0. The step-length test fails where the
        forces are balanced but the step is not yet short (train_random's sequence 72: sub-steps at the iteration limit
        with |g| of 1.6e-4 to 3.7e-3 N); with rtol 1e-3 press_slide takes 0.85-0.89x the Newton iterations, its markers
        within the run-to-run spread but for two frames (BENCHMARKS.md ``fem_force_test_gpu``); scenes take 3e-3
        (BENCHMARKS.md ``fem_force_test_default``)."""
        rtol = self.settings.newton_force_rtol
        return bool(rtol) and g_norm <= rtol * load and self._short_step_converges(g_norm)

    def _force_forcing(self, g_norm: float, load: float) -> float:
        """The loosest relative residual a Newton system at |g| = ``g_norm`` (N) needs where the force test is on:
        ``FORCE_FORCING`` times its bound (``newton_force_rtol`` times the support's normal ``load``, at most
        ``max_residual_n``) over |g|; 0 where the test is off. Newton solves a system only where |g| is above the bound,
        so this is below ``FORCE_FORCING``."""
        rtol = self.settings.newton_force_rtol
        if not rtol or not g_norm > 0.0:
            return 0.0
        return FORCE_FORCING * min(rtol * load, self.settings.max_residual_n) / g_norm

    def _newton_iteration_cap(self) -> int:
        """``max_newton_iterations``, or its default for the linear solver in use (settings.py)."""
        cap = self.settings.max_newton_iterations
        return cap if cap is not None else (80 if self._linear.method == "direct" else 120)
