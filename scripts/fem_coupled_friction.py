"""Study: friction's normal pressure implicit in Newton (no lag loop) against the lagged solver.

    .venv/bin/python scripts/fem_coupled_friction.py [SCENE] [--frames 8] [--moves 4,12] [--linear lu|gmres|bicgstab]
        [--sequence I] [--trajectory-from SCENE] [--lagged-first] [--merit-memory M] [--contraction] [--md-out FILE]
        [--benchmarks]
    python scripts/fem_coupled_friction.py scenes/train_random.toml --sequence 2 --moves 1,4 --linear gmres   (a GPU)

The solver lags friction's normal pressure lam = k g and tangent plane n at u_lag (physics/contact.py) and moves the lag
a few times per load step (friction_lag.py ``_move_lag``): a fixed point on the pressure, each move costing Newton a few
iterations, and on sharp, high-friction contacts not converged after 12 moves (BENCHMARKS.md
``fem_friction_lag_moves_train_random_gpu``). Here the lag is the current u at every Newton iteration and the Jacobian
takes the pressure's derivative in: the friction gradient G_f = mu k g f1(y) t (t = u_t / y) depends on u through
g(u) too, dg/dx = -n, so

    J = H(u) + J_c,   J_c = -mu k f1(y) t n^T   (per contact point: the rows of t, the columns of n)

integrated over the contact sides. n's own derivative is left out, here and in the solver's normal term (k g dn/du):
J is exact on a flat indenter face, not on a curved one such as the default sphere, where its direction need not lower
the merit. J is not symmetric, so each system is solved by LU (``--linear lu``: SuperLU on the host, a new
factorisation per iteration: seconds on the tiny mesh) or by GMRES or BiCGStab on the solver's device (``--linear
gmres|bicgstab``: ``coupled_newton_krylov``; BENCHMARKS.md ``fem_coupled_friction_gpu``), and the line search backtracks
on |gradient|^2
(the exact Newton direction of the coupled problem lowers it; E with a moving lag is no merit function) while keeping
det F > 0. No stiffness raise, no stall test: a study, not the solver. Its solution is the
lag's fixed point, so its frames' ``friction_lag_residual_n`` is round-off.

``--lagged-first`` adds a run whose load steps are first solved by the solver's Newton with friction's first lag never
moved, then by this Newton from that solution (``lagged_then_coupled``): whether the lag's correction from a nearby
lag's solution costs the coupled Newton only a step or two (BENCHMARKS.md ``fem_lag_then_coupled_cpu``).
``--merit-memory M`` (above 1) adds a run of the coupled Newton whose line search is nonmonotone: a step must lower
|g|^2 below the largest of the last M accepted values, not the last one (``reference_merit``), so that a full Newton
step that raises |g|^2 for a while is not cut back (BENCHMARKS.md ``fem_coupled_nonmonotone_cpu``, ``_gpu``).
``--contraction`` (with ``--linear lu``) reports, per load step of the coupled run, rho(H^-1 J_c) at its Newton systems
(``lag_contraction``): the factor by which a move of the lag shrinks the lag's error near the solution, and the rate
of a defect correction that would solve J's systems with H's symmetric solver (BENCHMARKS.md ``fem_lag_contraction_cpu``).

Reports per run (the lagged solver with each count in ``--moves``, then this Newton): Newton iterations per frame,
line-search halvings, the friction force per sliding frame, the largest lag residual, and the largest marker distance
from the coupled run; a run whose frame fails is listed with its error. Default: the tiny press-and-slide fixture on
this CPU.
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
from pathlib import Path
from unittest import mock

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import typer
import warp as wp
import warp.fem as fem

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, publish  # noqa: E402
from fem_frame_timing import run  # noqa: E402

from transtac_sim.physics import QuasiStaticSolver  # noqa: E402
from transtac_sim.physics.coarse_space import CoarseSpace, prolong  # noqa: E402
from transtac_sim.physics.contact import ContactState, _f1_over_y, tangential_slip  # noqa: E402
from transtac_sim.physics.device_linear import fixed_blocks, project_fixed  # noqa: E402
from transtac_sim.physics.elasticity import CLAMPED, EXACT  # noqa: E402
from transtac_sim.physics.host_factorisation import bsr_to_scipy  # noqa: E402
from transtac_sim.physics.indenter_query import Indenters, penetration  # noqa: E402
from transtac_sim.physics.newton import NewtonSteps  # noqa: E402
from transtac_sim.physics.reductions import max_abs, negated_free  # noqa: E402
from transtac_sim.physics.sparse_product import BlockJacobi  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SECTION = "fem_coupled_friction_cpu"
MAX_ITERATIONS = 80
#: ``--linear gmres|bicgstab``: Newton's systems solved to the relative residual min(FORCING_MAX, |g| / |g_first|)
#: (inexact Newton, as the solver's), at least KRYLOV_RTOL_MIN, in at most KRYLOV_MAXITER iterations (GMRES restarted
#: every GMRES_RESTART and checked then; BiCGStab checked every BICGSTAB_CHECK)
FORCING_MAX = 0.01
KRYLOV_RTOL_MIN = 1.0e-4  # the device CG's tight tolerance (linear.py ``cg_tol``)
KRYLOV_MAXITER = {EXACT: 620, CLAMPED: 3000}  # the exact Hessian's system gives up sooner: the clamped one is next
GMRES_RESTART = 62
BICGSTAB_CHECK = 10
#: Krylov iterations per Newton system of the last ``coupled_newton_krylov`` run, and the systems it did not solve to
#: its tolerance with the exact Hessian (then tried with the clamped one) or with either
krylov_iterations: list[int] = []
krylov_unsolved = {"exact": 0, "both": 0}


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


def coupling_matrix(solver: QuasiStaticSolver, ind):
    """J_c (N/mm, a 3x3-block BSR matrix on the solver's device) at the solver's u: ``coupling_form`` over the contact
    sides."""
    trial = fem.make_trial(solver._space, domain=solver._sides)
    test = fem.make_test(solver._space, domain=solver._sides)
    return fem.integrate(coupling_form, quadrature=solver._q_contact,
                         fields={"du": trial, "v": test, "u": solver.u.trace(), "u_prev": solver.u_prev.trace()},
                         values={"ind": ind, "st": solver._contact_state}, output_dtype=wp.float64)


def gradient_with_lag_at_u(solver: QuasiStaticSolver, ind) -> wp.array:
    """The gradient (N, all dofs, on the solver's device) at u with friction's lag moved to u first."""
    wp.copy(solver.u_lag.dof_values, solver.u.dof_values)
    solver._update_lag(ind)
    return solver._gradient(ind)


def reference_merit(merits: list[float], memory: int) -> float:
    """The merit a line-search step must lower (by Armijo's factor): the largest of the last ``memory`` accepted ones, a
    nonmonotone search (Grippo, Lampariello & Lucidi 1986) that lets a full Newton step raise |g|^2 for a while where a
    monotone one (``memory`` 1) would cut it back."""
    return max(merits[-memory:])


def lag_contraction(H: sp.spmatrix, J_c: sp.spmatrix) -> float:
    """rho(H^-1 J_c), the spectral radius: the factor by which one move of friction's lag shrinks the lag's error near
    a solution. Moving the lag and solving again is the fixed point u_(k+1) = solve(lag at u_k), whose linearisation is
    H e_(k+1) = -J_c e_k (H the lagged problem's Hessian, J_c the normal pressure's share of friction's gradient,
    ``coupling_form``). It is also the rate of the defect correction x <- H^-1 (b - J_c x) that would solve
    (H + J_c) x = b with H's symmetric solver. 0 where J_c is zero (no contact point with friction), NaN where H is singular
    or ARPACK fails."""
    if not np.any(J_c.data):  # no contact point with friction: the lag holds nothing
        return 0.0
    try:
        lu = spla.splu(sp.csc_matrix(H))
    except RuntimeError:  # singular
        return float("nan")
    if H.shape[0] <= 64:  # ARPACK needs k < n - 1; small systems are solved densely
        return float(np.max(np.abs(np.linalg.eigvals(lu.solve(J_c.toarray())))))
    op = spla.LinearOperator(H.shape, matvec=lambda x: lu.solve(J_c @ x), dtype=np.float64)
    try:
        values = spla.eigs(op, k=3, which="LM", return_eigenvectors=False, maxiter=5000, tol=1e-6)
    except spla.ArpackNoConvergence as partial:
        values = partial.eigenvalues
    except spla.ArpackError:
        return float("nan")
    return float(np.max(np.abs(values))) if len(values) else float("nan")


def coupled_newton(solver: QuasiStaticSolver, ind, may_stall: bool = False, merit_memory: int = 1,
                   contraction: list[list[float]] | None = None) -> tuple[bool, int, str, float]:
    """Newton on the lag-free problem for one load step, in place of ``NewtonSteps._newton`` (same result tuple;
    ``may_stall`` is ignored: no stall test). The line search compares |g|^2 with the largest of the last
    ``merit_memory`` accepted ones (``reference_merit``; 1: with the last, a monotone search). ``contraction``: a list
    to which this load step appends the ``lag_contraction`` of each of its Newton systems (H the exact Hessian)."""
    free, tol = solver._linear._free, solver.settings.newton_tol_mm

    def gradient_at_u() -> np.ndarray:  # on the free dofs
        return gradient_with_lag_at_u(solver, ind).numpy().reshape(-1)[free].copy()

    g = gradient_at_u()
    merits = [0.5 * g @ g]
    if contraction is not None:
        contraction.append([])
    for iteration in range(1, MAX_ITERATIONS + 1):
        J_c = bsr_to_scipy(coupling_matrix(solver, ind))
        H = bsr_to_scipy(solver._hessian(ind, 1.0, EXACT))
        if contraction is not None:
            contraction[-1].append(lag_contraction(H.tocsr()[free][:, free], J_c.tocsr()[free][:, free]))
        J = (H + J_c).tocsr()[free][:, free].tocsc()
        try:
            d = spla.splu(J).solve(-g)
        except RuntimeError:
            return False, iteration, "singular Jacobian", 0.0
        u0 = solver.u.dof_values.numpy().reshape(-1).copy()
        if np.max(np.abs(d)) < tol:
            u0[free] += d
            solver.u.dof_values.assign(u0.reshape(-1, 3))
            return True, iteration, "", solver._max_penetration(ind)
        merit, alpha = reference_merit(merits, merit_memory), 1.0
        while alpha > 1e-4:
            x = u0.copy()
            x[free] += alpha * d
            solver._u_try.dof_values.assign(x.reshape(-1, 3))
            if solver._min_det(solver._u_try) > 0.0:
                solver.u.dof_values.assign(x.reshape(-1, 3))
                g_try = gradient_at_u()
                if 0.5 * g_try @ g_try <= (1.0 - 1e-4 * alpha) * merit:
                    g = g_try
                    merits.append(0.5 * g @ g)
                    break
                solver.u.dof_values.assign(u0.reshape(-1, 3))
            alpha *= 0.5
            solver.stats["backtracks"] += 1
        else:
            solver.u.dof_values.assign(u0.reshape(-1, 3))
            return False, iteration, "line search failed", 0.0
    return False, MAX_ITERATIONS, "Newton iteration limit reached", 0.0


@wp.kernel(enable_backward=False)
def _two_level(inverse: wp.array(dtype=wp.mat33d), x: wp.array(dtype=wp.vec3d), y: wp.array(dtype=wp.vec3d),
               z: wp.array(dtype=wp.vec3d), alpha: wp.float64, beta: wp.float64, arm: wp.array(dtype=wp.vec3d),
               free: wp.array(dtype=wp.vec3d), aggregate: wp.array(dtype=int), values: wp.array(dtype=wp.float64)):
    """z = alpha (D^-1 x + P values) + beta y, values = A_c^-1 P^T x (coarse_space.py's M r)."""
    i = wp.tid()
    z[i] = alpha * (inverse[i] * x[i] + prolong(arm, free, aggregate, values, i)) + beta * y[i]


class TwoLevel(BlockJacobi):
    """The device CG's additive two-level preconditioner, M r = D^-1 r + P A_c^-1 P^T r (coarse_space.py), as a
    ``warp.optim.linear`` operator: block-Jacobi of the matrix given, the coarse inverse of ``coarse`` (made from a
    symmetric positive definite matrix beforehand)."""

    def __init__(self, A, coarse: CoarseSpace):
        super().__init__(A)
        sums = wp.zeros(1, dtype=wp.float64, device=A.device)

        def matvec(x, y, z, alpha, beta):
            coarse.solve(x, sums, 0)
            wp.launch(_two_level, dim=A.nrow, device=A.device,
                      inputs=[self.inverse_blocks, x, y, z, wp.float64(alpha), wp.float64(beta), coarse.arm,
                              coarse.free, coarse.aggregate, coarse.values])

        self._matvec = matvec


def coupled_newton_krylov(solver: QuasiStaticSolver, ind, may_stall: bool = False, method: str = "gmres",
                          merit_memory: int = 1) -> tuple[bool, int, str, float]:
    """``coupled_newton`` with every array on the solver's device (a GPU's, where it has one): J = H + J_c assembled
    there, its fixed rows and columns projected out, and each system solved by Warp's restarted GMRES or BiCGStab
    (``method``) preconditioned
    with the device CG's two-level preconditioner (``TwoLevel``; block-Jacobi alone where the solver has no coarse
    level: the host path), to the inexact-Newton tolerance ``FORCING_MAX`` / ``KRYLOV_RTOL_MIN`` within
    ``KRYLOV_MAXITER``; where that fails J is made with the clamped Hessian (the volumetric term's geometric part
    clamped, elasticity.py) and solved again, and the last step is taken whether solved or not. Krylov iterations per
    system go to ``krylov_iterations``. ``merit_memory``: as in ``coupled_newton``."""
    from warp.optim.linear import bicgstab, gmres

    tol, fixed = solver.settings.newton_tol_mm, solver._linear._fixed
    fixed_np = fixed.numpy() > 0.5

    def gradient_at_u() -> tuple[wp.array, float]:  # -g and |g| on the free dofs
        return negated_free(gradient_with_lag_at_u(solver, ind), solver._fixed_mask)

    rhs, g_norm = gradient_at_u()
    g_first, merits = g_norm, [g_norm * g_norm]
    # the coarse level where the solver's device path has one (on a GPU), its inverse made once per load step from the
    # first Hessian at u (exact, else clamped) whose Galerkin operator is positive definite
    setup = solver._linear._coarse_setup
    coarse = None
    if setup is not None:
        coarse = getattr(solver, "_study_coarse", None) or CoarseSpace(*setup, solver.device)
        solver._study_coarse = coarse
        for clamp in (EXACT, CLAMPED):
            H = wp.sparse.bsr_copy(solver._hessian(ind, 1.0, clamp))
            project_fixed(H, fixed, fixed_blocks(H, fixed_np))
            if coarse.update(H):
                break

    def solve(J, d: wp.array, rtol: float, clamp: int) -> tuple[bool, int]:  # J d = rhs from d: (solved, iterations)
        M = TwoLevel(J, coarse) if coarse is not None and coarse.ready else BlockJacobi(J)
        common = {"tol": rtol, "maxiter": KRYLOV_MAXITER[clamp], "M": M, "use_cuda_graph": solver.device.is_cuda}
        if method == "gmres":
            its, residual, atol = gmres(J, rhs, d, restart=GMRES_RESTART, check_every=GMRES_RESTART, **common)
        else:
            its, residual, atol = bicgstab(J, rhs, d, check_every=BICGSTAB_CHECK, **common)
        return bool(residual <= atol), int(its)

    for iteration in range(1, MAX_ITERATIONS + 1):
        J_c = coupling_matrix(solver, ind)
        rtol, its = max(min(FORCING_MAX, g_norm / g_first), KRYLOV_RTOL_MIN), 0
        for clamp in (EXACT, CLAMPED):  # the clamped Hessian where the Krylov method does not solve the exact one's
            J = wp.sparse.bsr_copy(solver._hessian(ind, 1.0, clamp))
            wp.sparse.bsr_axpy(J_c, J)
            project_fixed(J, fixed, fixed_blocks(J, fixed_np))
            d = wp.zeros_like(rhs)
            solved, n = solve(J, d, rtol, clamp)
            step, its = max_abs(d), its + n
            if solved and step < 100.0 * tol and rtol > KRYLOV_RTOL_MIN:  # near convergence the step decides: tightly
                solved, n = solve(J, d, KRYLOV_RTOL_MIN, clamp)
                step, its = max_abs(d), its + n
            if solved:
                break
            krylov_unsolved["exact" if clamp == EXACT else "both"] += 1
        krylov_iterations.append(int(its))
        if not np.isfinite(step):
            return False, iteration, f"{method} gave a non-finite step", 0.0
        if step < tol:
            fem.linalg.array_axpy(x=d, y=solver.u.dof_values, alpha=1.0)
            return True, iteration, "", solver._max_penetration(ind)
        u0 = wp.clone(solver.u.dof_values)
        merit, alpha = reference_merit(merits, merit_memory), 1.0
        while alpha > 1e-4:
            wp.copy(solver._u_try.dof_values, u0)
            fem.linalg.array_axpy(x=d, y=solver._u_try.dof_values, alpha=alpha)
            if solver._min_det(solver._u_try) > 0.0:
                wp.copy(solver.u.dof_values, solver._u_try.dof_values)
                rhs_try, norm_try = gradient_at_u()
                if norm_try * norm_try <= (1.0 - 1e-4 * alpha) * merit:
                    rhs, g_norm = rhs_try, norm_try
                    merits.append(g_norm * g_norm)
                    break
                wp.copy(solver.u.dof_values, u0)
            alpha *= 0.5
            solver.stats["backtracks"] += 1
        else:
            wp.copy(solver.u.dof_values, u0)
            return False, iteration, "line search failed", 0.0
    return False, MAX_ITERATIONS, "Newton iteration limit reached", 0.0


def newton_for(linear: str, merit_memory: int = 1, contraction: bool = False):
    """The coupled Newton whose systems ``linear`` solves (lu, gmres or bicgstab), as a ``NewtonSteps._newton``;
    ``contraction`` (lu only): each system's ``lag_contraction`` goes to ``lag_contractions``, a list per load step."""
    def newton(solver: QuasiStaticSolver, ind, may_stall: bool = False,
               lifting: bool = False) -> tuple[bool, int, str, float]:  # lifting: no contact prediction here
        if linear == "lu":
            return coupled_newton(solver, ind, may_stall, merit_memory, lag_contractions if contraction else None)
        return coupled_newton_krylov(solver, ind, may_stall, linear, merit_memory)
    return newton


NEWTONS = {linear: newton_for(linear) for linear in ("lu", "gmres", "bicgstab")}
#: ``lag_contraction`` of each Newton system, a list per load step, of the last run made with ``--contraction``
lag_contractions: list[list[float]] = []
#: (lagged, coupled) Newton iterations and the coupled part's line-search halvings per load step of the last
#: ``lagged_then_coupled`` run (the coupled ones None where the lagged part failed)
phase_iterations: list[tuple[int, int | None, int | None]] = []


@contextlib.contextmanager
def lag_held(solver: QuasiStaticSolver):
    """Within it, the solver's Newton never moves friction's lag (``friction_lag_moves`` 0); its settings are put back
    after."""
    kept = solver.settings
    solver.settings = dataclasses.replace(kept, friction_lag_moves=0)
    try:
        yield
    finally:
        solver.settings = kept


def lagged_then_coupled(newton):
    """A Newton for one load step, in place of ``NewtonSteps._newton``: the solver's own Newton with friction's first
    lag (the warm start's, newton.py ``_solve_step``) never moved, then ``newton`` (the coupled one) from its solution.
    The question it answers: is the coupled Newton quadratic from the solution of a nearby lag, so that the lag's
    correction costs a step or two? Iterations of both parts are summed; the split goes to ``phase_iterations``."""
    def solve(solver: QuasiStaticSolver, ind, may_stall: bool = False, *lifting) -> tuple[bool, int, str, float]:
        with lag_held(solver):  # ``lifting`` (this tree's Newton, contact_prediction.py) passed on where given
            ok, lagged, why, pen = NewtonSteps._newton(solver, ind, may_stall, *lifting)
        if not ok:
            phase_iterations.append((lagged, None, None))
            return ok, lagged, why, pen
        halvings = solver.stats["backtracks"]
        ok, coupled, why, pen = newton(solver, ind, may_stall)
        phase_iterations.append((lagged, coupled, solver.stats["backtracks"] - halvings))
        return ok, lagged + coupled, why, pen
    return solve


def _coupled_run(scene: Path, frames: int, newton, sequence: int | None, trajectory_from: Path | None) -> dict:
    krylov_iterations.clear()
    krylov_unsolved.update(exact=0, both=0)
    phase_iterations.clear()
    lag_contractions.clear()
    # put back as it was: _newton is inherited (newton.py), so no copy is left on the subclass
    with mock.patch.object(QuasiStaticSolver, "_newton", newton):
        result = run(scene, 2, frames, trajectory_from, sequence)
    return result | {"krylov": (list(krylov_iterations), dict(krylov_unsolved)), "phases": list(phase_iterations),
                     "contraction": [list(c) for c in lag_contractions]}


def main(scene: Path = typer.Argument(REPO / "tests" / "fixtures" / "tiny_press_slide.toml"),
         frames: int = typer.Option(8, min=1), moves: str = typer.Option("4,12", help="the lagged solver's lag moves"),
         linear: str = typer.Option("lu", help="the coupled Newton's systems: lu (SuperLU on the host), gmres or "
                                               "bicgstab (Warp's, on the solver's device)"),
         sequence: int | None = typer.Option(None, min=0, help="solve this sequence of a randomised scene"),
         trajectory_from: Path | None = typer.Option(None, help="the indenters' motion from this scene"),
         lagged_first: bool = typer.Option(False, help="also a run whose load steps are first solved with friction's "
                                                       "first lag never moved, then by the coupled Newton from there"),
         merit_memory: int = typer.Option(1, min=1, help="above 1, also a run of the coupled Newton whose line search "
                                                         "compares with the largest of the last M merits"),
         contraction: bool = typer.Option(False, help="with --linear lu: rho(H^-1 J_c) of each Newton system of the "
                                                      "coupled run, the rate at which moves of friction's lag converge"),
         md_out: Path | None = typer.Option(None, help="also write the table to this file"),
         benchmarks: bool = typer.Option(False, help=f"write the table into BENCHMARKS.md, section {SECTION}")) -> None:
    if linear not in NEWTONS:
        raise typer.BadParameter(f"--linear {linear!r}: allowed {', '.join(NEWTONS)}")
    if contraction and linear != "lu":
        raise typer.BadParameter(f"--contraction needs --linear lu (the host LU of H), not {linear!r}")
    runs, failed = {}, {}

    def attempt(name: str, solve) -> None:  # a run whose frame fails is reported, not the end of the study
        try:
            runs[name] = solve()
        except Exception as error:  # noqa: BLE001 (SolverDidNotConverge and whatever the study's Newton raises)
            failed[name] = f"{type(error).__name__}: {' '.join(str(error).split())[:300]}"
            print(f"{name}: {failed[name]}", flush=True)

    for m in moves.split(","):
        attempt(f"lagged, {m} moves", lambda m=m: run(scene, 2, frames, trajectory_from, sequence,
                                                                  friction_lag_moves=int(m)))
    attempt("coupled (no lag)", lambda: _coupled_run(scene, frames, newton_for(linear, contraction=contraction),
                                                     sequence, trajectory_from))
    if merit_memory > 1:
        attempt(f"coupled, nonmonotone line search ({merit_memory})", lambda: _coupled_run(
            scene, frames, newton_for(linear, merit_memory), sequence, trajectory_from))
    if lagged_first:
        attempt("first lag solved, then coupled", lambda: _coupled_run(
            scene, frames, lagged_then_coupled(NEWTONS[linear]), sequence, trajectory_from))
    if not runs:
        raise SystemExit("every run failed")
    ref_name = "coupled (no lag)" if "coupled (no lag)" in runs else list(runs)[-1]
    ref = runs[ref_name]
    ref_markers = np.array(ref["markers_mm"])
    friction = np.array([np.linalg.norm(f[0][:2]) for f in ref["forces_n"]])
    sliding = friction > 0.1 * friction.max()
    lines = [f"Machine: {machine_name(ref['device'])}. Command: `.venv/bin/python scripts/fem_coupled_friction.py "
             f"{' '.join(sys.argv[1:])}` ({ref['scene'].replace(str(REPO) + '/', '')}, P2, {frames} frames; "
             f"{int(sliding.sum())} of them with a friction force of at least 10 % of the largest).", "",
             "| run | Newton iterations per frame | all frames | sliding frames | line-search halvings | friction force "
             f"per sliding frame (N) | largest lag residual (N) | markers vs {ref_name} (mm) | seconds |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, r in runs.items():
        its, forces = r["iterations"], np.array([f[0] for f in r["forces_n"]])
        lines.append(f"| {name} | {', '.join(map(str, its))} | {sum(its)} | "
                     f"{sum(i for i, s in zip(its, sliding, strict=True) if s)} | {sum(r['backtracks'])} | "
                     f"{', '.join(f'{x:.3f}' for x in np.linalg.norm(forces[sliding, :2], axis=1))} | "
                     f"{max(r['lag_residual_n']):.2g} | "
                     f"{np.max(np.linalg.norm(np.array(r['markers_mm']) - ref_markers, axis=-1)):.4f} | "
                     f"{sum(r['seconds']):.1f} |")
    lines += [f"| {name} | failed: {why} | | | | | | | |" for name, why in failed.items()]
    for name, r in runs.items():
        iterations, unsolved = r.get("krylov", ([], {}))
        if linear != "lu" and iterations:
            lines += ["", f"{linear} iterations per Newton system of the {name} run (counted at its checks): median "
                      f"{int(np.median(iterations))}, max {max(iterations)}, {len(iterations)} systems; "
                      f"{unsolved['exact']} not solved with the exact Hessian within {KRYLOV_MAXITER[EXACT]} (the "
                      f"clamped one taken), {unsolved['both']} with neither (within {KRYLOV_MAXITER[CLAMPED]})."]
        if r.get("contraction"):
            lines += ["", f"{name}, rho(H^-1 J_c) per load step (a failed one included) at its last Newton system, "
                      "at the step's solution where it converged (the largest over its systems): " + ", ".join(
                          f"{c[-1]:.3g} ({np.nanmax(c):.3g})" for c in r["contraction"]) + "."]
        if r.get("phases"):
            lines += ["", f"{name}, Newton iterations per load step, first lag never moved + coupled (the coupled "
                      "part's line-search halvings): " + ", ".join(
                          f"{a}+{b} ({h})" if b is not None else f"{a}+failed" for a, b, h in r["phases"]) + "."]
    publish("\n".join(lines), md_out, benchmarks, SECTION)


if __name__ == "__main__":
    typer.run(main)
