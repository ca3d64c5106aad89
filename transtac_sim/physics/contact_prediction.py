"""The Newton step's contact prediction: an active-set (semi-smooth Newton) correction of the penalty contact, as a
mixin of ``QuasiStaticSolver`` (solver.py; newton.py's line search calls ``_predict_contact``).

The penalty energy k/2 max(0, g)^2 (contact.py) is piecewise quadratic in u, and Newton's system at u holds its term
only at the contact points in contact at u. A point out of contact at u that the Newton step du carries into an
indenter is modelled as free, so the full step overshoots into the indenter and the line search cuts it back. Where an
indenter lifts off, the gel springs back after it and Newton creeps: on the tiny mesh with press_slide's motion and no
friction (``scripts/fem_frame_timing.py tests/fixtures/tiny_press_slide.toml --frames 10 --friction 0
--no-contact-prediction``, this project's 2-core CPU) the release frame took 12 Newton iterations and 7 line-search
halvings, the other frames 2-6 iterations and none; with the prediction it takes 6 and 1, to the same forces.

Where the full step of a load step that lifts an indenter (warm_start.py ``lifts_off``) is refused by its energy, the
points out of contact at u (g(u) = 0) that u + du puts more than ``PREDICT_DEPTH_MM`` into an indenter are predicted to
touch. At u + du such a point has the penetration g_t > 0 and push-out normal n_t; g_s = g_t + n_t . du(x) < 0 is its
signed gap at u along n_t (exact for a flat face). Each gets the linearised contact term k/2 (g_s - n_t . d)^2 and the
system is solved once more:

    (H + sum k n_t n_t^T) d = -grad E + sum k g_s n_t      (sums over the predicted points' quadrature weights)

one step of the primal-dual active set method on the penalty term (Hintermueller, Ito & Kunisch, SIAM J. Optim. 13,
2002). Its full step is tried next; where that is refused too, the line search goes on along du. The line search works
on E itself, so the prediction changes Newton's path, not the energy it minimises: on press_slide the markers stay as
close to the solver's without it as two runs without it stay to each other.

Why only where an indenter lifts: on presses and slides it did not pay, in versions tried during development and not
kept (so no figures here). Made before every line search, it saved Newton iterations on press_slide's slide frames too,
but once led the stability table's 50 %-deep press, on the GPU, to another equilibrium with about three times the force.
Made on every refused full step, the slide frames took as many Newton iterations as without it, and each prediction
(an interpolation, a read, the extra term's assembly and a CG solve) was time lost. The kept version's figures are in
BENCHMARKS.md ``fem_contact_prediction_gpu``.
"""

from __future__ import annotations

from dataclasses import dataclass

import warp as wp
import warp.fem as fem

from transtac_sim.physics.indenter_query import Indenters, penetration
from transtac_sim.physics.reductions import extremes, step_summary

_f = wp.float64

#: (mm) a point out of contact at u is predicted to touch where the Newton step puts it deeper than this into an
#: indenter: the solver's default penetration_tol_mm of 0.02 mm times 2.5
PREDICT_DEPTH_MM = 0.05


@wp.struct
class PredictedContact:
    """Per contact quadrature point q and indenter i (index q * count + i): k where the point is predicted to touch,
    else 0 (N/mm^3); its signed gap g_s at u (mm, <= 0) and the push-out normal n_t at u + du."""

    stiffness: wp.array(dtype=wp.float64)
    gap: wp.array(dtype=wp.float64)
    normal: wp.array(dtype=wp.vec3d)


@fem.integrand
def predicted_contact_form(s: fem.Sample, domain: fem.Domain, u: fem.Field, du: fem.Field, ind: Indenters,
                           pred: PredictedContact, depth: wp.float64):
    """Stores, per indenter, k, g_s and n_t where the point is out of contact at u and deeper than ``depth`` (mm) at
    u + du; k = 0 elsewhere."""
    x = fem.position(domain, s) + u(s)
    step = du(s)
    for i in range(ind.count):
        j = s.qp_index * ind.count + i
        g0, n0 = penetration(ind, i, x)
        gt, nt = penetration(ind, i, x + step)
        k = _f(0.0)
        gap = gt + wp.dot(nt, step)
        if g0 <= _f(0.0) and gt > depth and gap < _f(0.0):
            k = ind.stiffness
        pred.stiffness[j] = k
        pred.gap[j] = gap
        pred.normal[j] = nt


@fem.integrand
def predicted_rhs_form(s: fem.Sample, v: fem.Field, count: int, pred: PredictedContact):
    """sum_i k g_s n_t . v: the predicted terms' part of the right-hand side (-gradient) at d = 0."""
    r = _f(0.0)
    for i in range(count):
        j = s.qp_index * count + i
        r += pred.stiffness[j] * pred.gap[j] * wp.dot(pred.normal[j], v(s))
    return r


@fem.integrand
def predicted_hessian_form(s: fem.Sample, du: fem.Field, v: fem.Field, count: int, pred: PredictedContact):
    """sum_i k (n_t . du)(n_t . v): the predicted terms' Hessian."""
    h = _f(0.0)
    for i in range(count):
        j = s.qp_index * count + i
        n = pred.normal[j]
        h += pred.stiffness[j] * wp.dot(n, du(s)) * wp.dot(n, v(s))
    return h


@dataclass
class PredictionWork:
    """The prediction's kept arrays (made on first use): the per-point state, the step as a field, the extra
    right-hand side and the trial function on the contact sides."""

    pred: PredictedContact
    step: fem.DiscreteField
    rhs: wp.array
    side_trial: fem.Field


class ContactPrediction:
    """``_predict_contact`` for ``QuasiStaticSolver`` (which provides the fields, assembly and linear solver)."""

    _prediction: PredictionWork | None = None

    def _prediction_work(self) -> PredictionWork:
        """The kept ``PredictionWork``, made on the first prediction of this solver (on the solver's device)."""
        if self._prediction is None:
            n = self._q_contact.total_point_count() * len(self.indenters)
            pred = PredictedContact()
            pred.stiffness = wp.zeros(n, dtype=wp.float64, device=self.device)
            pred.gap = wp.zeros(n, dtype=wp.float64, device=self.device)
            pred.normal = wp.zeros(n, dtype=wp.vec3d, device=self.device)
            with wp.ScopedDevice(self.device):
                self._prediction = PredictionWork(pred, self._space.make_field(), wp.empty_like(self.u.dof_values),
                                                  fem.make_trial(self._space, domain=self._sides))
        return self._prediction

    def _predicted_points(self, ind, du: wp.array) -> bool:
        """Stores in ``self._prediction.pred`` the points that the step ``du`` (vec3d per node, mm) from self.u is
        predicted to bring into contact (``predicted_contact_form``); True if there are any (one read)."""
        work = self._prediction_work()
        wp.copy(work.step.dof_values, du)
        fem.interpolate(predicted_contact_form, at=self._q_contact,
                        fields={"u": self.u.trace(), "du": work.step.trace()},
                        values={"ind": ind, "pred": work.pred, "depth": PREDICT_DEPTH_MM})
        return extremes(work.pred.stiffness)[1] > 0.0

    def _predict_contact(self, ind, H, rhs: wp.array, du: wp.array, rtol: float, exact_below: float,
                         tight: float | None = None) -> tuple[wp.array, float, float] | None:
        """The Newton step solved again with the contact of the points that ``du`` carries into an indenter (see the
        module docstring): (the new step d, d . rhs, max |d|), or None where no point is predicted to touch, or the
        system (``H``, the last Hessian solved, changed in place; ``rhs`` = -grad E on the free components) is then not
        found positive definite, or d is not a finite descent direction of E. ``rtol``, ``exact_below`` and ``tight``
        as in ``LinearSolver.solve``. The linear solver keeps the new system for its step estimate (``solve_last``)."""
        if not self._predicted_points(ind, du):
            return None
        work = self._prediction
        values = {"count": ind.count, "pred": work.pred}
        fem.integrate(predicted_rhs_form, quadrature=self._q_contact, fields={"v": self._side_test}, values=values,
                      output=work.rhs)
        fem.linalg.array_axpy(x=rhs, y=work.rhs, alpha=1.0)
        part = self._assemble("predicted", predicted_hessian_form, self._q_contact,
                              {"du": work.side_trial, "v": self._side_test}, values)
        self._add_part(H, "predicted", part)
        self.stats["predicted_contacts"] += 1
        step = self._linear.solve(H, work.rhs, definite=True, rtol=rtol, exact_below=exact_below, guess=du,
                                  tight=tight)
        if step is None:
            return None
        step_dot_rhs, step_max, finite = step_summary(step, rhs)
        return (step, step_dot_rhs, step_max) if finite and step_dot_rhs > 0.0 else None
