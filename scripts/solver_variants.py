"""Newton variants that the FEM timing scripts (fem_phase_profile.py, fem_frame_timing.py) switch on to compare with
the default in one run (BENCHMARKS.md ``fem_slide_iterations_gpu``). Imported as a sibling module: run those scripts as
``python scripts/NAME.py``."""

from __future__ import annotations

import functools

import typer

from transtac_sim.physics import device_linear, newton, settings
from transtac_sim.physics.newton import NewtonSteps

WARM_STARTS = ("all", "extrapolated", "none")


def apply(warm_start: str = "all", exact_below: float = newton.EXACT_BELOW,
          lag_move_ratio: float | None = None, estimate_rtol: float = device_linear.ESTIMATE_RTOL,
          estimate_cap_factor: float = device_linear.ESTIMATE_CAP_FACTOR) -> None:
    """``warm_start``: the guesses a (sub)step may start from (newton.py ``_warm_start``): all, extrapolated (not the
    slide's carried one), or none (the last converged state); ``exact_below``: newton.EXACT_BELOW; ``lag_move_ratio``:
    newton.LAG_MOVE_RATIOS of both linear solvers (None: as they are); ``estimate_rtol``, ``estimate_cap_factor``: the device's step estimate
    (device_linear.ESTIMATE_RTOL, ESTIMATE_CAP_FACTOR)."""
    if warm_start not in WARM_STARTS:
        raise typer.BadParameter(f"--warm-start must be one of {', '.join(WARM_STARTS)}, got {warm_start!r}")
    newton.EXACT_BELOW = exact_below
    if lag_move_ratio is not None:
        newton.LAG_MOVE_RATIOS = dict.fromkeys(newton.LAG_MOVE_RATIOS, lag_move_ratio)
    device_linear.ESTIMATE_RTOL = estimate_rtol
    device_linear.ESTIMATE_CAP_FACTOR = estimate_cap_factor
    if warm_start != "all":
        guesses = NewtonSteps._guesses
        NewtonSteps._carried = lambda self, shift: None
        NewtonSteps._guesses = lambda self, step: (
            [] if warm_start == "none" else [g for g in guesses(self, step) if g is not None])


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
                                 "guess on slides) or none")
EXACT_BELOW_OPTION = typer.Option(newton.EXACT_BELOW, min=0.0, help="newton.EXACT_BELOW (multiples of newton_tol_mm)")
LAG_MOVE_RATIO_OPTION = typer.Option(None, min=0.0, help="replace newton.LAG_MOVE_RATIOS (of both linear solvers; "
                                     f"default {newton.LAG_MOVE_RATIOS})")
ESTIMATE_RTOL_OPTION = typer.Option(device_linear.ESTIMATE_RTOL, min=0.0, max=1.0,
                                    help="device_linear.ESTIMATE_RTOL (the device's step estimate)")
ESTIMATE_CAP_FACTOR_OPTION = typer.Option(device_linear.ESTIMATE_CAP_FACTOR, min=0.0,
                                          help="device_linear.ESTIMATE_CAP_FACTOR")
FRICTION_LAG_MOVES_OPTION = typer.Option(None, min=1, help="replace the scene's [physics] friction_lag_moves (per step)")
FRICTION_MEMORY_OPTION = typer.Option(True, "--friction-memory/--no-friction-memory",
                                      help="carry friction's sticking stretch from step to step "
                                      "(SolverSettings.friction_memory; off: each step's slip afresh, the model before)")
