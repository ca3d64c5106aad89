"""The quasi-static solver's settings, per-frame record and result, and its errors (used by solver.py,
load_stepping.py, newton.py and trajectory.py; importable from ``transtac_sim.physics``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class SolverDidNotConverge(RuntimeError):
    """A frame could not be solved even after load sub-stepping."""


class IndenterStartsInsideGel(ValueError):
    """An indenter's start pose already penetrates the undeformed gel."""


@dataclass(frozen=True)
class SolverSettings:
    degree: int = 2  # element order (1: linear tets, 2: quadratic tets)
    newton_tol_mm: float = 1.0e-5  # converged when max |Newton step| is below this
    # per (sub)step; None: 80 with the direct solver, 120 with CG. On the device path (CG, the clamped Hessian
    # where the exact one is not positive definite) Newton converges linearly where the inversion barrier acts; a sub-step starts that work again from the last
    # converged state, so a higher cap is cheaper there: a cube edge pressed 1.5 mm (train_random sequence 4,
    # frames 0-3, one H100) took 38.7 s of physics with 120 against 101.8 s with 40 (16 sub-steps in frame 2;
    # measured when each halving started the frame again, before sub-steps went on from the last converged one).
    # The host path's 40 was raised to 80 for the same reason: the stability table took 279 against 357 s on the
    # 2-core CPU, no case needed a sub-step (up to 4 with 40), and a marginal slide that failed at every sub-step
    # with 40 converged (BENCHMARKS.md ``fem_host_newton_cap``)
    max_newton_iterations: int | None = None
    max_substep_halvings: int = 5  # the smallest sub-step: 1/2**5 of the frame's motion (load_stepping.py)
    # "direct" (CHOLMOD/SuperLU on the host), "cg" (Warp, on the device); "auto": cg on a GPU, else direct
    # (on an H100, cg solves the press-and-slide frames about 20x faster than the host factorisation)
    linear_solver: str = "auto"
    contact_stiffness: float | None = None  # N/mm^3; None: stiffness_factor * E_top / (h_top / degree)
    stiffness_factor: float = 100.0
    penetration_tol_mm: float = 0.02  # stated bound on residual interpenetration at convergence
    max_stiffness_raises: int = 3  # per step: contact stiffness raised while the penetration is above the bound
    # friction smoothing (mm): slips below this are elastic sticking (a sticking point moves up to this far against the
    # indenter before friction reaches mu times the normal pressure). 0.05 rather than 0.01: the stick-slip
    # switch is 5x less stiff, which cuts Newton's iterations on frictional frames by a third to a half
    # (scripts/fem_frame_timing.py on tests/fixtures/tiny_press.toml: 12, 15 -> 8, 9), forces within 2 %
    slip_eps_mm: float = 5.0e-2
    # per step: friction's lag (normal pressure and tangent plane) moved to the current u at most this often; scenes
    # set it with [physics] friction_lag_moves, whose description (config/scene.py) gives the measured trade-off
    friction_lag_moves: int = 4
    # friction's sticking stretch is carried from step to step (contact.py ``stick_form``); False measures each step's
    # slip afresh (the model before): a sticking point then loses its traction at every step and creeps back up to
    # slip_eps_mm, so a held contact relaxes and the result depends on how many frames a motion takes
    # (tests/test_physics_solver.py ``test_sticking_*``)
    friction_memory: bool = True
    contact_quadrature_order: int | None = None  # None: 2 * degree
    # the device CG's coarse level (coarse_space.py): as many aggregates of equal node counts as the gel has cells of
    # about this size (mm), whose rigid-body modes are solved for directly; None: block-Jacobi alone
    coarse_cell_mm: float | None = 3.0
    fixed_z_tol_mm: float = 1.0e-6  # default fixed mask: z <= this
    # inversion barrier (elasticity.py): acts where det F < barrier_det_f at the 4 check points of a tet, with
    # stiffness barrier_stiffness * mu; 0 turns it off. It keeps sharp tips, nu -> 0.5 and deep presses from
    # folding elements at the discrete minimum (scripts/fem_stability.py)
    barrier_det_f: float = 0.1
    barrier_stiffness: float = 10.0
    # a (sub)step that Newton ends with |gradient| (N, free dofs) above this is not taken as converged but halved
    # (load_stepping.py): converged frames end at 1e-7 to 1e-3 N, and one train_random frame had been written with
    # 1.58e3 N (BENCHMARKS.md ``fem_float64_fallback_gpu``). Newton's step below newton_tol_mm shows convergence only at
    # |gradient| up to this: near elements flattened towards det F = 0 the barrier makes that step tiny at any force
    # (convergence_tests.py ``_short_step_converges``, BENCHMARKS.md ``fem_short_step_gpu``)
    max_residual_n: float = 1.0
    # also converged where |gradient| (N, free dofs) is at most this fraction of the normal load the gel passes to its
    # support (at equilibrium the indenters' normal force) and friction's lag is settled, whatever the step's length
    # (convergence_tests.py ``_force_balanced``; Newton's systems are then solved no tighter than this test needs,
    # ``_force_forcing``); None or 0: the step-length test alone, which solves to newton_tol_mm in every
    # direction (the force test leaves soft directions less converged: uniform compression at nu = 0.49 ends 1.5e-4 mm
    # off the exact displacement with 3e-3, against 1.2e-9 mm with the step-length test; tests/test_physics_solver.py
    # ``test_force_test_leaves_soft_directions_less_converged``).
    # Scenes take 3e-3 unless they set it (config/scene.py, [physics] newton_force_rtol; BENCHMARKS.md
    # ``fem_force_test_default``)
    newton_force_rtol: float | None = None
    # a (sub)step that can still be halved is given up once Newton has taken this many steps since the lowest |gradient|
    # (N, free dofs) of the (sub)step, the last of them before its |gradient| is read (counted afresh after a lag move
    # or a stiffness raise; convergence_tests.py ``StallWatch``): next to elements flattened towards det F = 0 Newton
    # can creep along the inversion barrier up to its iteration cap, |gradient| growing by orders of magnitude, without
    # 10 line searches in a row cut short (the stall rule). On train_random (120 sequences, 8 MPS workers, an H100) 1
    # step reached the cap against 6 with 0 (off); over three runs of each the slowest frame took 8.0-11.0 s of physics
    # against 14.9-27.2 s, the mean 0.43-0.45 s against 0.48-0.56 s; the stability table's depth 50 % (the device path
    # on the CPU, deterministic) 144 Newton iterations against 288, to the same state. A step given up might have
    # converged in a few more steps (BENCHMARKS.md ``fem_no_progress_gpu``). 0 turns it off
    newton_no_progress_steps: int = 30

    def __post_init__(self) -> None:
        if self.newton_no_progress_steps < 0:
            raise ValueError(f"newton_no_progress_steps must be >= 0 (0: off), got {self.newton_no_progress_steps}")


@dataclass(frozen=True)
class FailedStep:
    """A load (sub)step that failed and was halved (load_stepping.py): the frame's motion from ``start`` to ``end``
    (fractions of it), the Newton iterations it took and why it failed."""

    start: float
    end: float
    iterations: int
    why: str

    def __str__(self) -> str:
        return (f"the step from {self.start:g} to {self.end:g} of the frame's motion failed after {self.iterations} "
                f"Newton iterations ({self.why})")


@dataclass
class SolverRecord:
    converged: bool
    iterations: int
    residual: float  # |gradient| (N) on the free dofs at the solution
    # the smallest det F at the inversion barrier's 4 check points per tet (elasticity.py). P2-P0 holds the volume at
    # each tet's centroid only: on press_slide's slide this reads 0.1-0.4 in surface tets under the contact while every
    # centroid J stays within 0.97-1.01 (scripts/fem_det_f_sites.py, BENCHMARKS.md fem_det_f_sites)
    min_det_f: float
    seconds: float
    # load steps the frame was solved in (1: in one; more after a failed step was halved, load_stepping.py)
    substeps: int
    max_penetration_mm: float = 0.0
    linear_iterations: int = 0
    backtracks: int = 0  # line-search halvings, all (sub)steps of the frame
    stiffness_raises: int = 0  # contact stiffness raised during the frame (kept for the next ones)
    warm_starts: int = 0  # (sub)steps started from the extrapolated increment rather than the last state
    lag_updates: int = 0  # friction's lag moved inside Newton, all (sub)steps of the frame
    indefinite_hessians: int = 0  # Newton steps whose exact Hessian was not positive definite (clamped instead)
    predicted_contacts: int = 0  # Newton steps solved again with the contact they predicted (contact_prediction.py)
    # |gradient| (N) at the solution once friction's lag (normal pressure and tangent plane) is moved there: what the lag
    # leaves unbalanced where its ``friction_lag_moves`` ran out before it converged (``residual`` is taken with the lag
    # where Newton left it; a converged lag leaves 1e-6 to 1e-4 N, contact_records.py
    # ``_launch_friction_lag_residual``); 0 without friction. On press_slide's motion on the tiny mesh (4 moves) it is
    # below 3e-3 N but in one frame, 0.065 N against a friction force of 1.2 N (BENCHMARKS.md
    # ``fem_friction_lag_residual``)
    friction_lag_residual_n: float = 0.0
    failed_steps: tuple[FailedStep, ...] = ()  # the frame's (sub)steps that failed and were halved, in order


@dataclass
class FrameResult:
    displacement_mm: np.ndarray  # (N,3) at the input vertices
    forces_n: np.ndarray  # (n_indenters, 3) force each indenter applies to the gel (pressing: fz < 0)
    torques_nmm: np.ndarray  # (n_indenters, 3) about each indenter's reference point (pose origin)
    record: SolverRecord
    poses: list = field(default_factory=list)
