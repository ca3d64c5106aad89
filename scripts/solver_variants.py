"""Newton variants that the FEM timing scripts (fem_phase_profile.py, fem_frame_timing.py) switch on to compare with
the default in one run (BENCHMARKS.md ``fem_slide_iterations_gpu``). Imported as a sibling module: run those scripts as
``python scripts/NAME.py``."""

from __future__ import annotations

import functools

import numpy as np
import typer
import warp as wp

from transtac_sim.physics import device_linear, newton, settings
from transtac_sim.physics.newton import NewtonSteps

try:
    from transtac_sim.physics import friction_lag
except ImportError:  # an older package tree through PYTHONPATH: newton.py held friction's lag moves
    friction_lag = newton

try:
    from transtac_sim.physics.contact_prediction import ContactPrediction
except ImportError:  # an older package tree through PYTHONPATH: it had no contact prediction to switch off
    ContactPrediction = type("ContactPrediction", (), {})
try:
    from transtac_sim.physics.warm_start import WarmStart
except ImportError:  # an older package tree through PYTHONPATH (a before/after comparison): newton.py had it
    from transtac_sim.physics.newton import NewtonSteps as WarmStart

WARM_STARTS = ("all", "extrapolated", "none", "carried")


def apply(warm_start: str = "all", exact_below: float = newton.EXACT_BELOW,
          lag_move_ratio: float | None = None, estimate_rtol: float = device_linear.ESTIMATE_RTOL,
          estimate_cap_factor: float = device_linear.ESTIMATE_CAP_FACTOR, estimate_band: str | None = None,
          press_lag_move_ratio: float | None = None, contact_prediction: bool = True) -> None:
    """``warm_start``: the guesses a (sub)step may start from (warm_start.py ``_warm_start``): all, extrapolated (not
    the slide's carried one), none (the last converged state) or carried (on a slide the carried guess alone, against
    the last state; otherwise all: ``_carried_on_slides``); ``exact_below``: newton.EXACT_BELOW; ``lag_move_ratio``:
    friction_lag.LAG_MOVE_RATIOS of both linear solvers (None: as they are); ``estimate_rtol``,
    ``estimate_cap_factor``: the device's step estimate (device_linear.ESTIMATE_RTOL, ESTIMATE_CAP_FACTOR);
    ``estimate_band``: friction_lag.ESTIMATE_REFINE_BAND as "LO,HI" (None: as it is); ``press_lag_move_ratio``: on load
    steps that only press, the ratio in place of friction_lag.LAG_MOVE_RATIOS (``_moves_lag_at_on_presses``; None: as
    on other steps);
    ``contact_prediction``: off, Newton takes its steps without contact_prediction.py's second solve (the solver
    before it)."""
    if warm_start not in WARM_STARTS:
        raise typer.BadParameter(f"--warm-start must be one of {', '.join(WARM_STARTS)}, got {warm_start!r}")
    if estimate_band is not None:
        friction_lag.ESTIMATE_REFINE_BAND = _band(estimate_band)
    newton.EXACT_BELOW = exact_below
    if lag_move_ratio is not None:
        friction_lag.LAG_MOVE_RATIOS = dict.fromkeys(friction_lag.LAG_MOVE_RATIOS, lag_move_ratio)
    if press_lag_move_ratio is not None:
        _moves_lag_at_on_presses(press_lag_move_ratio)
    if not contact_prediction:
        ContactPrediction._predict_contact = lambda self, *args: None
    device_linear.ESTIMATE_RTOL = estimate_rtol
    device_linear.ESTIMATE_CAP_FACTOR = estimate_cap_factor
    if warm_start == "carried":
        WarmStart._guesses = functools.partialmethod(_carried_on_slides, WarmStart._guesses)
    elif warm_start != "all":
        guesses = WarmStart._guesses
        WarmStart._carried = lambda self, shift: None
        WarmStart._guesses = lambda self, step: (
            [] if warm_start == "none" else [g for g in guesses(self, step) if g is not None])


def _carried_on_slides(self, guesses, step: np.ndarray):
    """The warm start's guesses with ``--warm-start carried``: where the step moves one indenter tangentially and not
    away from the gel (a slide; the conditions of warm_start.py ``_guesses``), the carried guess alone; otherwise
    ``guesses(self, step)``."""
    tol = self.settings.newton_tol_mm
    shift = np.array([step[0], step[1], 0.0])
    if len(self.indenters) == 1 and np.linalg.norm(shift) > tol and step[2] <= tol:
        return [self._carried(shift)]
    return list(guesses(self, step))


def presses_only(step: np.ndarray, tol_mm: float) -> bool:
    """Whether a load step's pose increment ``step`` (newton.py ``_pose_step``: per indenter its translation and its
    rotation vector times its radius, mm) only presses: no indenter moves sideways, turns or lifts by more than
    ``tol_mm``, and one moves down (-z, into the gel) by more."""
    per_indenter = step.reshape(-1, 6)
    still = np.all(np.abs(per_indenter[:, [0, 1, 3, 4, 5]]) <= tol_mm) and np.all(per_indenter[:, 2] <= tol_mm)
    return bool(still and np.any(per_indenter[:, 2] < -tol_mm))


def _moves_lag_at_on_presses(ratio: float) -> None:
    """``--press-lag-move-ratio``: on a load step that ``presses_only`` and may move friction's lag more than once,
    the lag moves once Newton's estimated remaining step is below ``ratio`` x |u - u_lag| (friction_lag.py
    ``_move_lag``) instead of the linear solver's friction_lag.LAG_MOVE_RATIOS. Measured with 1 (moves as early as the
    estimate allows): BENCHMARKS.md ``fem_press_lag_moves_gpu``."""
    solve_step, lag_threshold = NewtonSteps._solve_step, NewtonSteps._lag_threshold
    pressing = {}  # solver id -> whether its current load step only presses

    def noting_presses(self, poses, prev_poses, may_stall=False):
        pressing[id(self)] = self.settings.friction_lag_moves > 1 and presses_only(
            self._pose_step(prev_poses, poses), self.settings.newton_tol_mm)
        return solve_step(self, poses, prev_poses, may_stall)

    def threshold(self, change):
        if not pressing.get(id(self)):
            return lag_threshold(self, change)
        tol = self.settings.newton_tol_mm
        return None if change < 10.0 * tol else max(tol, ratio * change)

    NewtonSteps._solve_step, NewtonSteps._lag_threshold = noting_presses, threshold


def keep_step_solutions() -> list[tuple[np.ndarray, np.ndarray]]:
    """``--save-step-solutions``: from now on every converged load (sub)step appends (its indenters' target poses,
    (indenters, 4, 4) mm; its solution u, (nodes, 3) mm) to the list returned, for ``oracle_lag``."""
    kept: list[tuple[np.ndarray, np.ndarray]] = []
    solve_step = NewtonSteps._solve_step

    def keeping(self, poses, prev_poses, may_stall=False):
        result = solve_step(self, poses, prev_poses, may_stall)
        if result[0]:
            kept.append((np.stack(poses), self.u.dof_values.numpy().copy()))
        return result

    NewtonSteps._solve_step = keeping
    return kept


#: ``--oracle-lag-part``: which of friction's lagged quantities the recorded solution gives (``oracle_lag``)
ORACLE_PARTS = ("both", "pressure", "normal")


def oracle_lag(poses: np.ndarray, solutions: np.ndarray, part: str = "both",
               penetration_errors: list[float] | None = None) -> None:
    """``--oracle-lag``: each load (sub)step's friction lag is that step's solution ``solutions[k]`` from an earlier run
    (``keep_step_solutions`` with a converged lag, e.g. 30 lag moves), set where Newton starts, and never moved. So the
    lag is the one Newton ends with from the first iteration: the Newton iterations left are what no lag scheme (timing,
    relaxation, prediction of the lag) could take away. The k-th (sub)step must go to ``poses[k]``: a run that sub-steps
    where the earlier one did not (or the reverse) is refused at the first step that differs.

    ``part`` (``--oracle-lag-part``): "both" as above; "pressure" or "normal": only friction's lagged penetration
    (its normal pressure k g) or only its lagged normal (the tangent plane) is the recorded solution's, the other is the
    solver's own first lag, u_lag stays the solver's own (its distance from u decides the lag moves as by default) and
    the lag moves as by default: what the error of that one part of the first lag costs. ``penetration_errors``: where
    given, each step appends the relative L2 difference, over the contact quadrature points, between the solver's own
    first lag's penetration max(g, 0) and the recorded solution's (0 where neither touches, inf where only the
    first lag does)."""
    if part not in ORACLE_PARTS:
        raise typer.BadParameter(f"--oracle-lag-part must be one of {', '.join(ORACLE_PARTS)}, got {part!r}")
    solve_step, newton_steps = NewtonSteps._solve_step, NewtonSteps._newton
    step_index: dict[int, int] = {}  # solver id -> index of its current (sub)step in the earlier run

    def matched_step(self, poses_, prev_poses, may_stall=False):
        k = step_index.get(id(self), -1) + 1
        if k >= len(poses) or not np.allclose(np.stack(poses_), poses[k], atol=1e-9):
            raise RuntimeError(f"--oracle-lag: load step {k} of this run goes to other poses than the earlier run's "
                               f"(of {len(poses)} steps): the runs sub-stepped differently, so no lag can be taken")
        step_index[id(self)] = k
        return solve_step(self, poses_, prev_poses, may_stall)

    def from_oracle(self, ind, may_stall=False, *lifting):  # ``lifting``: this tree's Newton's, where given
        st = self._contact_state
        own_g, own_n, own_u = wp.clone(st.lag_g), wp.clone(st.lag_n), wp.clone(self.u_lag.dof_values)
        self.u_lag.dof_values.assign(solutions[step_index[id(self)]])
        self._update_lag(ind)
        if penetration_errors is not None:
            penetration_errors.append(_relative_difference(own_g.numpy(), st.lag_g.numpy()))
        if part == "pressure":
            wp.copy(st.lag_n, own_n)
        elif part == "normal":
            wp.copy(st.lag_g, own_g)
        if part != "both":
            wp.copy(self.u_lag.dof_values, own_u)
        return newton_steps(self, ind, may_stall, *lifting)

    NewtonSteps._solve_step, NewtonSteps._newton = matched_step, from_oracle
    if part == "both":
        NewtonSteps._move_lag = lambda self, ind, remaining, change=None: False
        # the step estimate is then compared with newton_tol_mm alone (friction_lag.py ``_estimate_band``): no lag
        # distance, neither read with the gradient's norm (newton.py ``_read_gradient``, where this tree has it) nor
        # on its own
        NewtonSteps._lag_change = lambda self: 0.0
        read_gradient = getattr(NewtonSteps, "_read_gradient", None)
        if read_gradient is not None:
            NewtonSteps._read_gradient = lambda self, ind, lag_change, *rest: read_gradient(self, ind, False, *rest)


def _relative_difference(g: np.ndarray, reference: np.ndarray) -> float:
    """|max(g, 0) - max(reference, 0)| / |max(reference, 0)| (L2 over the entries): 0 where both are 0, inf where
    only ``g`` is not."""
    a, b = np.maximum(g, 0.0), np.maximum(reference, 0.0)
    scale = np.linalg.norm(b)
    return float(np.linalg.norm(a - b) / scale) if scale > 0.0 else (0.0 if not a.any() else np.inf)


def _band(text: str) -> tuple[float, float]:
    """``--estimate-band``'s "LO,HI" (multiples of newton_tol_mm, 0 <= LO <= HI), for a tree that has the band."""
    if not hasattr(friction_lag, "ESTIMATE_REFINE_BAND"):
        raise typer.BadParameter("--estimate-band: this package has no friction_lag.ESTIMATE_REFINE_BAND (an older "
                                 "tree: it refines every step estimate below 10 newton_tol_mm)")
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        raise typer.BadParameter(f"--estimate-band takes LO,HI (two numbers), got {text!r}") from None
    if not 0.0 <= low <= high:
        raise typer.BadParameter(f"--estimate-band needs 0 <= LO <= HI, got {text!r}")
    return low, high


def solver_settings(**fields) -> None:
    """Every ``SolverSettings`` that simulation.py makes from now on takes ``fields`` (it imports the class from
    ``transtac_sim.physics`` when it solves), in place of those of an earlier call."""
    from transtac_sim import physics

    physics.SolverSettings = functools.partial(settings.SolverSettings, **fields)


def friction_memory() -> bool:
    """``SolverSettings.friction_memory`` as ``solver_settings`` left it."""
    from transtac_sim import physics

    return physics.SolverSettings().friction_memory


WARM_START_OPTION = typer.Option("all", help="the guesses a (sub)step may start from: all, extrapolated (no carried "
                                 "guess on slides), none, or carried (on slides the carried guess alone)")
EXACT_BELOW_OPTION = typer.Option(newton.EXACT_BELOW, min=0.0, help="newton.EXACT_BELOW (multiples of newton_tol_mm)")
LAG_MOVE_RATIO_OPTION = typer.Option(None, min=0.0, help="replace friction_lag.LAG_MOVE_RATIOS (of both linear "
                                     f"solvers; default {friction_lag.LAG_MOVE_RATIOS})")
PRESS_LAG_MOVE_RATIO_OPTION = typer.Option(None, min=0.0, help="on load steps that only press (and may move "
                                           "friction's lag more than once), this ratio in place of "
                                           "friction_lag.LAG_MOVE_RATIOS")
ESTIMATE_RTOL_OPTION = typer.Option(device_linear.ESTIMATE_RTOL, min=0.0, max=1.0,
                                    help="device_linear.ESTIMATE_RTOL (the device's step estimate)")
ESTIMATE_CAP_FACTOR_OPTION = typer.Option(device_linear.ESTIMATE_CAP_FACTOR, min=0.0,
                                          help="device_linear.ESTIMATE_CAP_FACTOR")
ESTIMATE_BAND_OPTION = typer.Option(None, help="friction_lag.ESTIMATE_REFINE_BAND as LO,HI: where the step estimate is "
                                    "refined to the tight tolerance, multiples of newton_tol_mm (default "
                                    f"{getattr(friction_lag, 'ESTIMATE_REFINE_BAND', None)}; 0,10 as before it)")
FRICTION_LAG_MOVES_OPTION = typer.Option(None, min=1, help="replace the scene's [physics] friction_lag_moves (per step)")
FRICTION_MEMORY_OPTION = typer.Option(True, "--friction-memory/--no-friction-memory",
                                      help="carry friction's sticking stretch from step to step "
                                      "(SolverSettings.friction_memory; off: each step's slip afresh, the model before)")
CONTACT_PREDICTION_OPTION = typer.Option(True, "--contact-prediction/--no-contact-prediction",
                                         help="solve a Newton step again with the contact it predicts "
                                         "(physics/contact_prediction.py; off: the solver before it)")
