"""Newton and linear-solver variants that the FEM timing scripts (fem_phase_profile.py, fem_frame_timing.py) switch on
to compare with the default in one run: each reproduces a measured alternative or the code before a change."""

from __future__ import annotations

import typer

from transtac_sim.physics import elasticity
from transtac_sim.physics.newton import NewtonSteps

SECOND_HESSIANS = {"clamped": elasticity.CLAMPED, "projected": elasticity.PROJECTED}


def apply(second_hessian: str = "clamped", exact_shifts: str = "", warm_start: str = "all") -> None:
    """``second_hessian``: Newton's Hessian where the exact one is not positive definite (newton.SECOND_HESSIAN);
    ``exact_shifts``: comma-separated multiples of |diag H| (newton.EXACT_SHIFTS); ``warm_start``: the guesses a (sub)step
    may start from (newton.py ``_warm_start``): all, extrapolated (not the slide's carried one), or none (u_prev)."""
    if warm_start not in ("all", "extrapolated", "none"):
        raise typer.BadParameter(f"--warm-start must be all, extrapolated or none, got {warm_start!r}")
    if warm_start != "all":
        guesses = NewtonSteps._guesses
        NewtonSteps._carried = lambda self, shift: None
        NewtonSteps._guesses = lambda self, step: (
            [] if warm_start == "none" else [g for g in guesses(self, step) if g is not None])

SECOND_HESSIAN_OPTION = typer.Option("clamped", help="Newton's Hessian where the exact one is not positive definite: "
                                     "clamped (the default) or projected (volumetric_hessian.py)")
EXACT_SHIFTS_OPTION = typer.Option("", help="the exact Hessian plus these multiples of |diag H| (comma-separated) tried "
                                   "before the second Hessian")
WARM_START_OPTION = typer.Option("all", help="the guesses a (sub)step may start from: all, extrapolated or none")
