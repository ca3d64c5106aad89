"""Study: friction's normal pressure implicit in Newton (no lag loop) against the lagged solver, on the host.

    .venv/bin/python scripts/fem_coupled_friction.py [SCENE] [--frames 8] [--moves 4,12] [--md-out FILE] [--benchmarks]

The solver lags friction's normal pressure lam = k g and tangent plane n at u_lag (physics/contact.py) and moves the lag
a few times per load step (newton.py ``_move_lag``): a fixed point on the pressure, each move costing Newton a few
iterations, and on sharp, high-friction contacts not converged after 12 moves (BENCHMARKS.md
``fem_friction_lag_moves_train_random_gpu``). Here the lag is the current u at every Newton iteration and the Jacobian
takes the pressure's derivative in: the friction gradient G_f = mu k g f1(y) t (t = u_t / y) depends on u through
g(u) too, dg/dx = -n, so

    J = H(u) + J_c,   J_c = -mu k f1(y) t n^T   (per contact point: the rows of t, the columns of n)

integrated over the contact sides. n's own derivative is left out, here and in the solver's normal term (k g dn/du):
J is exact on a flat indenter face, not on a curved one such as the default sphere, where its direction need not lower
the merit. J is not symmetric, so each system is solved by LU (SuperLU, a new factorisation per iteration: seconds on the
tiny mesh), and the line search backtracks on |gradient|^2 (the exact Newton direction of the coupled problem lowers it;
E with a moving lag is no merit function) while keeping det F > 0. No stiffness raise, no stall test: a study, not the solver. Its solution is the
lag's fixed point, so its frames' ``friction_lag_residual_n`` is round-off.

Reports per run (the lagged solver with each count in ``--moves``, then this Newton): Newton iterations per frame,
line-search halvings, the friction force per sliding frame, the largest lag residual, and the largest marker distance
from the coupled run. Default: the tiny press-and-slide fixture on this CPU.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import scipy.sparse.linalg as spla
import typer
import warp as wp
import warp.fem as fem

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, publish  # noqa: E402
from fem_frame_timing import run  # noqa: E402

from transtac_sim.physics import QuasiStaticSolver  # noqa: E402
from transtac_sim.physics.contact import ContactState, _f1_over_y, tangential_slip  # noqa: E402
from transtac_sim.physics.elasticity import EXACT  # noqa: E402
from transtac_sim.physics.host_factorisation import bsr_to_scipy  # noqa: E402
from transtac_sim.physics.indenter_query import Indenters, penetration  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SECTION = "fem_coupled_friction_cpu"
MAX_ITERATIONS = 80


@fem.integrand
def coupling_form(s: fem.Sample, domain: fem.Domain, du: fem.Field, v: fem.Field, u: fem.Field, u_prev: fem.Field,
                  ind: Indenters, st: ContactState):
    """J_c's bilinear form (N/mm^3 per unit area, integrated over the contact sides to N/mm): -mu k f1(y)/y (u_t . v)
    (n . du) where u is in contact (the lag at u)."""
    X = fem.position(domain, s)
    x = X + u(s)
    h = wp.float64(0.0)
    for i in range(ind.count):
        j = s.qp_index * ind.count + i
        g, n = penetration(ind, i, x)
        if g > wp.float64(0.0) and ind.friction[i] > wp.float64(0.0):
            ut = tangential_slip(ind, st, i, j, x, X + u_prev(s), st.lag_n[j])
            c = ind.friction[i] * ind.stiffness * _f1_over_y(wp.length(ut), ind.slip_eps)
            h -= c * wp.dot(ut, v(s)) * wp.dot(n, du(s))
    return h


def coupled_newton(solver: QuasiStaticSolver, ind, may_stall: bool = False) -> tuple[bool, int, str, float]:
    """Newton on the lag-free problem for one load step, in place of ``NewtonSteps._newton`` (same result tuple;
    ``may_stall`` is ignored: no stall test)."""
    free, tol = solver._linear._free, solver.settings.newton_tol_mm
    trial = fem.make_trial(solver._space, domain=solver._sides)
    test = fem.make_test(solver._space, domain=solver._sides)

    def gradient_at_u() -> np.ndarray:  # the lag moved to u first
        wp.copy(solver.u_lag.dof_values, solver.u.dof_values)
        solver._update_lag(ind)
        return solver._gradient(ind).numpy().reshape(-1)[free].copy()

    g = gradient_at_u()
    for iteration in range(1, MAX_ITERATIONS + 1):
        J_c = fem.integrate(coupling_form, quadrature=solver._q_contact,
                            fields={"du": trial, "v": test, "u": solver.u.trace(), "u_prev": solver.u_prev.trace()},
                            values={"ind": ind, "st": solver._contact_state}, output_dtype=wp.float64)
        J = (bsr_to_scipy(solver._hessian(ind, 1.0, EXACT)) + bsr_to_scipy(J_c)).tocsr()[free][:, free].tocsc()
        try:
            d = spla.splu(J).solve(-g)
        except RuntimeError:
            return False, iteration, "singular Jacobian", 0.0
        u0 = solver.u.dof_values.numpy().reshape(-1).copy()
        if np.max(np.abs(d)) < tol:
            u0[free] += d
            solver.u.dof_values.assign(u0.reshape(-1, 3))
            return True, iteration, "", solver._max_penetration(ind)
        merit, alpha = 0.5 * g @ g, 1.0
        while alpha > 1e-4:
            x = u0.copy()
            x[free] += alpha * d
            solver._u_try.dof_values.assign(x.reshape(-1, 3))
            if solver._min_det(solver._u_try) > 0.0:
                solver.u.dof_values.assign(x.reshape(-1, 3))
                g_try = gradient_at_u()
                if 0.5 * g_try @ g_try <= (1.0 - 1e-4 * alpha) * merit:
                    g = g_try
                    break
                solver.u.dof_values.assign(u0.reshape(-1, 3))
            alpha *= 0.5
            solver.stats["backtracks"] += 1
        else:
            solver.u.dof_values.assign(u0.reshape(-1, 3))
            return False, iteration, "line search failed", 0.0
    return False, MAX_ITERATIONS, "Newton iteration limit reached", 0.0


def _coupled_run(scene: Path, frames: int) -> dict:
    lagged = QuasiStaticSolver._newton
    QuasiStaticSolver._newton = coupled_newton
    try:
        return run(scene, 2, frames, None)
    finally:
        QuasiStaticSolver._newton = lagged


def main(scene: Path = typer.Argument(REPO / "tests" / "fixtures" / "tiny_press_slide.toml"),
         frames: int = typer.Option(8, min=1), moves: str = typer.Option("4,12", help="the lagged solver's lag moves"),
         md_out: Path | None = typer.Option(None, help="also write the table to this file"),
         benchmarks: bool = typer.Option(False, help=f"write the table into BENCHMARKS.md, section {SECTION}")) -> None:
    runs = {f"lagged, {m} moves": run(scene, 2, frames, None, friction_lag_moves=int(m)) for m in moves.split(",")}
    runs["coupled (no lag)"] = _coupled_run(scene, frames)
    ref = runs["coupled (no lag)"]
    ref_markers = np.array(ref["markers_mm"])
    friction = np.array([np.linalg.norm(f[0][:2]) for f in ref["forces_n"]])
    sliding = friction > 0.1 * friction.max()
    lines = [f"Machine: {machine_name(ref['device'])}. Command: `.venv/bin/python scripts/fem_coupled_friction.py "
             f"{' '.join(sys.argv[1:])}` ({ref['scene'].replace(str(REPO) + '/', '')}, P2, {frames} frames; {int(sliding.sum())} of them with a "
             "friction force of at least 10 % of the largest).", "",
             "| run | Newton iterations per frame | all frames | sliding frames | line-search halvings | friction force "
             "per sliding frame (N) | largest lag residual (N) | markers vs coupled (mm) | seconds |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in runs.items():
        its, forces = r["iterations"], np.array([f[0] for f in r["forces_n"]])
        lines.append(f"| {name} | {', '.join(map(str, its))} | {sum(its)} | "
                     f"{sum(i for i, s in zip(its, sliding, strict=True) if s)} | {sum(r['backtracks'])} | "
                     f"{', '.join(f'{x:.3f}' for x in np.linalg.norm(forces[sliding, :2], axis=1))} | "
                     f"{max(r['lag_residual_n']):.2g} | "
                     f"{np.max(np.linalg.norm(np.array(r['markers_mm']) - ref_markers, axis=-1)):.4f} | "
                     f"{sum(r['seconds']):.0f} |")
    publish("\n".join(lines), md_out, benchmarks, SECTION)


if __name__ == "__main__":
    typer.run(main)
