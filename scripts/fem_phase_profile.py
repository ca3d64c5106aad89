"""Where a FEM frame's time goes: seconds per solver phase (exclusive, device synchronised), calls, and the
linear solver's iterations per solve, for the frames of a scene as ``generate`` solves them.

    .venv/bin/python scripts/fem_phase_profile.py tests/fixtures/tiny_press.toml [--device cpu|cuda]
        [--linear-solver auto|direct|cg] [--frames N] [--skip-first]

Phases are the methods of ``QuasiStaticSolver`` (solver.py, newton.py) and of its ``LinearSolver``
(linear.py); each is timed with ``wp.synchronize_device`` on entry and exit, so a kernel launched in one
phase is charged to it and not to the next host read. Time outside every listed phase is ``other`` (the
Newton loop's own host work: numpy on the gradient, step norms, copies). ``--skip-first`` leaves the first
frame out of the totals (kernel compilation on a fresh machine).

``--gpu-activity`` (CUDA only) times the frames without the per-phase synchronisation and records what the GPU
itself did (CUPTI through ``wp.timing_begin``): kernel, copy and allocation time against the wall time, and the
kernels that took the most. A GPU busy for a small share of the wall time is waiting on the host (launches,
Python, host reads), and more work per launch (larger or batched systems) comes almost free. ``--host-profile FILE``
runs the counted frames under cProfile, also without the phase timing, and writes its statistics to FILE (``python -m
pstats FILE``): where the host's own time goes (on a GPU a read's wait falls into ``array.numpy``'s copy).
``--passes N`` solves the frames N times in one process, each pass with a new solver as ``generate``'s sequences in
one worker have, and counts the last: what is made once per process (Warp's kernels for a part of the solver first
used in a later frame, such as the warm start of a slide) is then paid for by the earlier passes.

To compare Newton variants in one run: ``--forcing-max F`` (newton.FORCING_MAX; 0: every CG solve to its
tight tolerance), ``--force-forcing F`` (physics/convergence_tests.py FORCE_FORCING: with the force test on, no
system solved tighter than F times the test's bound over |g|; 0: the tree before BENCHMARKS.md
``fem_force_forcing_gpu``), ``--clamped-only`` (no exact-Hessian attempt), ``--no-estimate`` (no step estimate from the
last system: the CG path before issue 12's third pass), ``--cg-tol T`` (the tight CG tolerance, relative
residual), ``--warp-spmv`` (Warp's ``bsr_mv`` in the CG instead of physics/sparse_product.py), ``--float64-cg-matrix``
(the device CG's product on the float64 matrix, as before it read a float32 copy), ``--fresh-cg-graphs`` (each device
CG solve makes its own work vectors, state and graph, as before commit 31c75b7; x, the block-Jacobi inverses and the
float32 blocks stay kept, physics/device_linear.py), ``--warp-cg``
(Warp's ``cg`` instead of physics/definite_cg.py: it cannot tell an indefinite system, so use it with
``--clamped-only``; the two flags together are the device path before definite_cg.py), ``--cg-unroll N`` (CG
iterations per pass of its loop, a multiple of 3; 1 before ``fem_cg_unrolled_gpu``, 4 before ``fem_cg_fused_gpu``).
``--no-replay`` launches the energy, det F, gradient and Hessian one kernel at a time instead of replaying their CUDA
graphs (replay.py), so that ``--gpu-activity`` lists their kernels (the device CG keeps its own graph).
``--coarse-cell-mm`` (the scene's ``[physics] coarse_cell_mm``; 0: block-Jacobi alone) and ``--coarse-refresh-steps``
(device_linear.COARSE_REFRESH_STEPS) set the device CG's coarse level (physics/coarse_space.py; BENCHMARKS.md
``fem_coarse_level_gpu``), whose size, inverses made and their seconds are printed.
``--newton-force-rtol R`` sets the scene's ``[physics] newton_force_rtol`` (Newton's force test; 0: off; BENCHMARKS.md
``fem_force_test_gpu``). ``--contact-rings N`` sets physics/contact_sides.py ``CONTACT_RINGS_GPU`` (the rings of
neighbours a new contact side subset takes on a GPU).
``--warm-start``, ``--exact-below``, ``--lag-move-ratio``, ``--press-lag-move-ratio``, ``--friction-lag-moves`` and
``--estimate-band`` are the Newton variants of scripts/solver_variants.py (BENCHMARKS.md ``fem_slide_iterations_gpu``,
``fem_estimate_refinement_gpu``, ``fem_press_lag_moves_gpu``).
On the device path the run also prints how many step estimates were refined to the tight CG tolerance, their
refinements' CG iterations, and the refined estimates' length (max |x|, mm) against their loose one's.
``--save-markers FILE.npz`` keeps each frame's marker positions (gel frame, mm), so that variants run
one after another can be compared for accuracy (``--compare-to`` an earlier run's file prints the largest
marker difference per frame). ``--save-step-solutions FILE.npz`` keeps each converged load step's poses and solution,
and ``--oracle-lag FILE.npz`` takes that solution as the step's friction lag from Newton's start, never moved
(solver_variants.py ``oracle_lag``): the Newton iterations that no lag scheme could save (BENCHMARKS.md
``fem_oracle_lag_gpu``); with ``--oracle-lag-part pressure|normal`` only that part of the first lag is the recorded
solution's and the lag moves as by default, and the run prints how far the solver's own first lag's penetration is
from the recorded one per load step (BENCHMARKS.md ``fem_lag_pressure_oracle``).
"""

from __future__ import annotations

import cProfile
import dataclasses
import functools
import pstats
import statistics
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np
import solver_variants
import typer
import warp as wp
from warp.optim.linear import aslinearoperator, cg

from transtac_sim.dataset.sequence import StageClock
from transtac_sim.physics import (
    QuasiStaticSolver,
    cg_kernels,
    contact_sides,
    convergence_tests,
    definite_cg,
    device_linear,
    newton,
)
from transtac_sim.physics.coarse_space import CoarseSpace
from transtac_sim.physics.definite_cg import CgResult
from transtac_sim.physics.elasticity import CLAMPED
from transtac_sim.physics.linear import LinearSolver
from transtac_sim.physics.reductions import max_abs
from transtac_sim.physics.replay import GraphCache
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import simulate_frames

PHASES = {
    QuasiStaticSolver: ("_gradient", "_energy", "_energy_and_min_det", "_hessian", "_min_det", "_max_penetration",
                        "_update_lag", "_move_lag", "_warm_start", "_carried", "_indenter_struct",
                        "_predicted_points", "_predict_contact"),  # contact_prediction.py
    CoarseSpace: ("update",),  # the coarse level's Galerkin operator and its inverse (coarse_space.py)
    LinearSolver: ("solve", "solve_last", "_cg"),  # solve / solve_last exclusive of _cg: the set-up (sums, projection,
    # preconditioner; on the host path the conversion and factorisation), _cg: the device CG iterations
}


#: the LinearSolver's counters the phase clock reports since its last reset: device solves stopped at non-positive
#: curvature, host (direct path) factorisations (failed ones included), the device step estimates' CG iterations and
#: those of them that did not converge
COUNTS = ("not_definite", "factorisations", "estimate_iterations", "estimates_unconverged")


class PhaseClock:
    """Exclusive seconds and calls per phase; nested phases are charged to the innermost one."""

    def __init__(self):
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.linear_iterations: list[int] = []
        self.linear_solver: LinearSolver | None = None
        self._counts_before: dict[str, int] = {}  # the LinearSolver's counts at the last reset
        self._counts_of: LinearSolver | None = None  # the LinearSolver they are of (a later pass has its own)
        self._stack: list[list] = []  # [name, start, child seconds]

    def wrap(self, cls, name: str):
        original = getattr(cls, name)
        clock = self

        @functools.wraps(original)
        def timed(obj, *args, **kwargs):
            wp.synchronize_device()
            clock._stack.append([name, time.perf_counter(), 0.0])
            try:
                return original(obj, *args, **kwargs)
            finally:
                wp.synchronize_device()
                label, start, children = clock._stack.pop()
                spent = time.perf_counter() - start
                clock.seconds[label] += spent - children
                clock.calls[label] += 1
                if clock._stack:
                    clock._stack[-1][2] += spent
                if isinstance(obj, LinearSolver) and name == "solve":
                    clock.linear_iterations.append(int(obj.last_iterations))
                    clock.linear_solver = obj

        setattr(cls, name, timed)
        return original

    def reset(self) -> None:
        self.seconds.clear()
        self.calls.clear()
        self.linear_iterations.clear()
        self._counts_before = {name: getattr(self.linear_solver, name) for name in COUNTS} if self.linear_solver else {}
        self._counts_of = self.linear_solver

    def count(self, name: str) -> int:
        """One of the LinearSolver's ``COUNTS`` since the last reset (all of a solver made after it, ``--passes``)."""
        if not self.linear_solver:
            return 0
        before = self._counts_before if self.linear_solver is self._counts_of else {}
        return getattr(self.linear_solver, name) - before.get(name, 0)


def main(scene: Path, device: str = typer.Option("cpu", help="cpu or cuda"),
         linear_solver: str = typer.Option("auto", help="auto, direct or cg"),
         frames: int = typer.Option(2, min=1), skip_first: bool = typer.Option(False),
         forcing_max: float = typer.Option(newton.FORCING_MAX, min=0.0, max=1.0),
         force_forcing: float = typer.Option(convergence_tests.FORCE_FORCING, min=0.0, max=1.0),
         clamped_only: bool = typer.Option(False), no_estimate: bool = typer.Option(False),
         warm_start: str = solver_variants.WARM_START_OPTION,
         exact_below: float = solver_variants.EXACT_BELOW_OPTION,
         lag_move_ratio: float | None = solver_variants.LAG_MOVE_RATIO_OPTION,
         press_lag_move_ratio: float | None = solver_variants.PRESS_LAG_MOVE_RATIO_OPTION,
         contact_prediction: bool = solver_variants.CONTACT_PREDICTION_OPTION,
         estimate_rtol: float = solver_variants.ESTIMATE_RTOL_OPTION,
         estimate_cap_factor: float = solver_variants.ESTIMATE_CAP_FACTOR_OPTION,
         friction_lag_moves: int | None = solver_variants.FRICTION_LAG_MOVES_OPTION,
         gpu_activity: bool = typer.Option(False, help="GPU busy time against wall time (CUDA; no phase timing)"),
         passes: int = typer.Option(1, min=1, help="solve the scene's frames this many times in one process, each "
                                    "with a new solver as generate's sequences have, and count the last pass"),
         host_profile: Path | None = typer.Option(None, help="cProfile the host over the counted frames (no phase "
                                                  "timing) into this pstats file"),
         warp_spmv: bool = typer.Option(False, help="Warp's bsr_mv in the CG (before sparse_product.py)"),
         float64_cg_matrix: bool = typer.Option(False, help="the device CG's product on the float64 matrix"),
         fresh_cg_graphs: bool = typer.Option(False, help="no workspace kept between device CG solves"),
         no_replay: bool = typer.Option(False, help="launch the solver's replayed sequences (replay.py) one by one, "
                                        "so that --gpu-activity lists their kernels"),
         cg_tol: float | None = typer.Option(None, help="the CG's tight tolerance, device and host PCG (default LinearSolver's)"),
         warp_cg: bool = typer.Option(False, help="Warp's cg instead of definite_cg (with --clamped-only)"),
         cg_unroll: int = typer.Option(definite_cg.UNROLL, min=1, help="definite_cg.UNROLL: CG iterations per pass "
                                                                      "of its loop (a multiple of 3)"),
         coarse_cell_mm: float | None = typer.Option(None, min=0.0, help="replace the scene's [physics] "
                                                     "coarse_cell_mm (the device CG's coarse level; 0: none)"),
         newton_force_rtol: float | None = typer.Option(None, min=0.0, max=0.1, help="replace the scene's [physics] "
                                                        "newton_force_rtol (Newton's force test; 0: off)"),
         contact_rings: int = typer.Option(contact_sides.CONTACT_RINGS_GPU, min=1,
                                           help="contact_sides.CONTACT_RINGS_GPU: rings of neighbours a new contact "
                                           "side subset takes on a GPU"),
         coarse_refresh_steps: int = typer.Option(device_linear.COARSE_REFRESH_STEPS, min=1,
                                                  help="device_linear.COARSE_REFRESH_STEPS"),
         estimate_band: str | None = solver_variants.ESTIMATE_BAND_OPTION,
         save_markers: Path | None = typer.Option(None, help="save each frame's marker positions (npz)"),
         compare_to: Path | None = typer.Option(None, help="an earlier --save-markers file to compare with"),
         save_step_solutions: Path | None = typer.Option(None, help="save each converged load step's poses and "
                                                         "solution u (npz), for --oracle-lag"),
         oracle_lag: Path | None = typer.Option(None, help="an earlier --save-step-solutions file: each load step's "
                                                "friction lag is that run's solution of the step, never moved"),
         oracle_lag_part: str = typer.Option("both", help="with --oracle-lag: both (the lag never moved), pressure or "
                                             "normal (only that part of the first lag is the recorded solution's, "
                                             "the lag then moves as by default)"),
         ) -> None:
    newton.FORCING_MAX = forcing_max
    convergence_tests.FORCE_FORCING = force_forcing
    device_linear.COARSE_REFRESH_STEPS = coarse_refresh_steps
    contact_sides.CONTACT_RINGS_GPU = contact_rings
    solver_variants.apply(warm_start, exact_below, lag_move_ratio, estimate_rtol, estimate_cap_factor, estimate_band,
                          press_lag_move_ratio, contact_prediction)
    step_solutions = solver_variants.keep_step_solutions() if save_step_solutions else None
    penetration_errors: list[float] = []
    if passes > 1 and (oracle_lag or save_step_solutions):
        raise typer.BadParameter("--oracle-lag and --save-step-solutions follow one solver's load steps: "
                                 "use --passes 1")
    if oracle_lag_part != "both" and not oracle_lag:
        raise typer.BadParameter("--oracle-lag-part takes one part of a recorded lag: give --oracle-lag FILE too")
    if oracle_lag:
        with np.load(oracle_lag) as kept:
            solver_variants.oracle_lag(kept["poses"], kept["u"], oracle_lag_part, penetration_errors)
    if clamped_only:
        QuasiStaticSolver._hessian_ladder = lambda self: ((1.0, CLAMPED), (0.0, CLAMPED))
    if no_estimate:
        LinearSolver.solve_last = lambda self, rhs, rtol=1e-3, exact_below=0.0, refine_above=0.0: None
    if warp_spmv:
        device_linear.block_row_operator = lambda H, **_: aslinearoperator(H)
    if float64_cg_matrix:
        float64_operator = device_linear.block_row_operator
        device_linear.block_row_operator = lambda H, **_: float64_operator(H)
    if warp_cg:
        device_linear.definite_cg = _warp_cg
    if cg_unroll % cg_kernels.SETS:
        raise typer.BadParameter(f"--cg-unroll must be a multiple of {cg_kernels.SETS}, got {cg_unroll}")
    definite_cg.UNROLL = cg_unroll
    if fresh_cg_graphs:
        kept_cg = device_linear.definite_cg
        device_linear.definite_cg = lambda *args, workspace=None, **kwargs: kept_cg(*args, **kwargs)
    if no_replay:
        GraphCache.run = lambda cache, key, keep, launches: launches()
    if cg_tol is not None:
        LinearSolver.__init__ = functools.partialmethod(LinearSolver.__init__, cg_tol=cg_tol)
    reference = np.load(compare_to) if compare_to else None
    markers = []
    setup = load_setup(scene)
    physics = setup.scene.physics.model_copy(update={"device": device, "linear_solver": linear_solver} | (
        {"friction_lag_moves": friction_lag_moves} if friction_lag_moves else {}) | (
        {"coarse_cell_mm": coarse_cell_mm} if coarse_cell_mm is not None else {}) | (
        {"newton_force_rtol": newton_force_rtol} if newton_force_rtol is not None else {}))
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    clock = PhaseClock()
    missing = [name for cls, names in PHASES.items() for name in names if not hasattr(cls, name)]
    if missing:  # an older tree through PYTHONPATH (a before/after comparison)
        print(f"phases not in this tree's solver, not timed: {', '.join(missing)}")
    timed_phases = not (gpu_activity or host_profile)
    originals = [] if not timed_phases else [(cls, name, clock.wrap(cls, name)) for cls, names in PHASES.items()
                                         for name in names if hasattr(cls, name)]
    activity: list = []
    failures = []
    solve_step = QuasiStaticSolver._solve_step

    def noting_failures(self, *args, **kwargs):  # a failed (sub)step makes the frame sub-step: say why
        result = solve_step(self, *args, **kwargs)
        if not result[0]:
            failures.append(f"frame {self.frame_index}: {result[2]} after {result[1]} Newton iterations")
        return result

    QuasiStaticSolver._solve_step = noting_failures
    frame_seconds, frame_iterations = [], []
    estimates, stop_recording = _record_estimates()
    profiler = cProfile.Profile() if host_profile else None

    def counting_from_here() -> None:  # what the frames before leave out of the figures
        clock.reset()
        estimates.clear()
        if gpu_activity:
            wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        if profiler:
            profiler.enable()

    try:
        for n in range(passes):
            for lst in (frame_seconds, frame_iterations, markers, failures):  # the figures are the last pass's
                lst.clear()
            if n == passes - 1 and not skip_first:
                counting_from_here()
            for f in simulate_frames(setup, frames, StageClock()):
                frame_seconds.append(f.solver["seconds"])
                frame_iterations.append(f.solver["iterations"])
                markers.append(f.markers_gel_mm)
                diff = ""
                if reference is not None and f.frame < len(reference["markers"]):
                    diff = (f", markers differ by "
                            f"{np.abs(f.markers_gel_mm - reference['markers'][f.frame]).max():.2g} mm")
                print(f"{f'pass {n + 1}, ' if passes > 1 else ''}frame {f.frame}: {f.solver['seconds']:.2f} s, "
                      f"{f.solver['iterations']} Newton iterations, {f.solver['substeps']} sub-step(s), "
                      f"Fz {', '.join(f'{x[2]:.4f}' for x in f.forces_n)} N{diff}", flush=True)
                if skip_first and f.frame == 0 and n == passes - 1:
                    counting_from_here()
        if gpu_activity:
            activity = wp.timing_end()
    finally:
        if profiler:
            profiler.disable()
            profiler.dump_stats(host_profile)
        for cls, name, original in originals:
            setattr(cls, name, original)
        QuasiStaticSolver._solve_step = solve_step
        stop_recording()
    if save_markers:
        np.savez(save_markers, markers=np.stack(markers))
    if step_solutions is not None:
        np.savez(save_step_solutions, poses=np.stack([p for p, _ in step_solutions]),
                 u=np.stack([u for _, u in step_solutions]))
    counted = frame_seconds[1:] if skip_first and len(frame_seconds) > 1 else frame_seconds
    iterations = sum(frame_iterations[1:] if skip_first and len(frame_iterations) > 1 else frame_iterations)
    total = sum(counted)
    print(f"\n{scene} on {wp.get_device(device if device != 'cuda' else 'cuda:0')}, linear solver {linear_solver}, "
          f"forcing max {forcing_max:g}, force forcing {force_forcing:g}, lag move ratios "
          f"{solver_variants.friction_lag.LAG_MOVE_RATIOS}"
          f"{'' if press_lag_move_ratio is None else f' ({press_lag_move_ratio:g} on presses)'}, estimate rtol "
          f"{device_linear.ESTIMATE_RTOL:g} (cap {device_linear.ESTIMATE_CAP_FACTOR:g}x), "
          f"friction lag moves {physics.friction_lag_moves}, exact below "
          f"{newton.EXACT_BELOW:g} tol{', no exact Hessian' if clamped_only else ''}"
          f"{', no step estimate' if no_estimate else ''}{', Warp cg' if warp_cg else ''}"
          f"{f', the lag of {oracle_lag} ({oracle_lag_part})' if oracle_lag else ''}: "
          f"{len(counted)} frame(s), {total:.2f} s, {iterations} Newton iterations "
          f"({1000 * total / max(iterations, 1):.1f} ms per iteration); Newton iterations per frame, median over "
          f"all frames {statistics.median(frame_iterations):g}")
    if penetration_errors:
        print("the solver's own first friction lag per load step: its penetration max(g, 0) at the contact quadrature "
              "points against the recorded solution's, relative L2 difference: "
              + ", ".join(f"{e:.2f}" for e in penetration_errors))
    if profiler:
        pstats.Stats(profiler).sort_stats("tottime").print_stats(40)
    if gpu_activity:
        print_gpu_activity(activity, total)
    if profiler or gpu_activity:
        return
    work = clock.linear_solver._work if clock.linear_solver else None
    print(f"device solves stopped at non-positive curvature: {clock.count('not_definite')}; host factorisations: "
          f"{clock.count('factorisations')}; step estimates: {clock.calls.get('solve_last', 0)} (on the device: "
          f"{clock.count('estimate_iterations')} CG iterations, {clock.count('estimates_unconverged')} not "
          f"converged); device CG graphs captured in the kept workspace (all frames): "
          f"{work.cg.captures if work else 0}; coarse level: "
          f"{(clock.linear_solver.coarse_stats() if clock.linear_solver else {}) or 'none'}")
    if estimates:
        refined = [e for e in estimates if len(e) == 2]
        ratios = [e[1][1] / e[0][1] for e in refined if e[0][1] > 0.0]
        # an older tree has no band: it refines every estimate below 10 newton_tol
        band = getattr(solver_variants.friction_lag, "ESTIMATE_REFINE_BAND", None)
        rule = f"band {band} x the threshold compared with" if band else "every one below 10 newton_tol"
        print(f"device step estimates refined to the tight tolerance ({rule}): "
              f"{len(refined)} of {len(estimates)}, the loose solves {sum(e[0][0] for e in estimates)} CG iterations, "
              f"the refinements {sum(e[1][0] for e in refined)}; refined length / loose length "
              + (f"{min(ratios):.3f}-{max(ratios):.3f}" if ratios else "-"))
    print("| phase | calls | s | ms per call | share |")
    print("|---|---|---|---|---|")
    for name, s in sorted(clock.seconds.items(), key=lambda kv: -kv[1]):
        print(f"| {name} | {clock.calls[name]} | {s:.3f} | {1000 * s / clock.calls[name]:.2f} | {s / total:.1%} |")
    print(f"| other | | {total - sum(clock.seconds.values()):.3f} | | "
          f"{(total - sum(clock.seconds.values())) / total:.1%} |")
    for why in failures:
        print(f"failed (sub)step, {why}")
    if clock.linear_iterations:
        li = clock.linear_iterations
        print(f"linear solver iterations per solve: median {statistics.median(li):g}, max {max(li)}, "
              f"total {sum(li)} over {len(li)} solves")


def _record_estimates() -> tuple[list, Callable[[], None]]:
    """Records each device step estimate's CG solves (device_linear.py ``_solve_last_cg``, ``definite_cg``): (the list
    they go into, per estimate (CG iterations, max |x| in mm) of its loose solve and, where it was refined, of the
    refinement; the function that puts the originals back)."""
    estimates: list = []
    solve_last_cg, cg_solve = device_linear.DeviceSolves._solve_last_cg, device_linear.definite_cg
    current: list | None = None

    def recording_solve(*args, **kwargs):
        result = cg_solve(*args, **kwargs)
        if current is not None:
            current.append((result.iterations, result.x_max))
        return result

    def recording_estimate(self, *args, **kwargs):
        nonlocal current
        current = []
        try:
            return solve_last_cg(self, *args, **kwargs)
        finally:
            if current:
                estimates.append(tuple(current))
            current = None

    def stop() -> None:
        device_linear.DeviceSolves._solve_last_cg, device_linear.definite_cg = solve_last_cg, cg_solve

    device_linear.DeviceSolves._solve_last_cg = recording_estimate
    device_linear.definite_cg = recording_solve
    return estimates, stop


def _warp_cg(A, b, x, rtol, maxiter, M=None, atol=0.0, workspace=None, coarse=None):
    """``definite_cg``'s interface on Warp's ``cg`` (which never reports an indefinite matrix; block-Jacobi only, no
    coarse level)."""
    iterations, err, tol = cg(A, b, x, tol=rtol, atol=atol, maxiter=maxiter, M=M, check_every=25)
    return CgResult(float(err) <= float(tol), False, int(iterations), max_abs(x),
                    float(np.sum(x.numpy() * b.numpy())))


def print_gpu_activity(results: list, wall_s: float) -> None:
    """GPU time by kind of activity and the kernels that took the most, against ``wall_s`` seconds of frames."""
    kinds: dict[str, list[float]] = defaultdict(list)
    kernels: dict[str, list[float]] = defaultdict(list)
    for r in results:
        kind = r.name.split(" ")[0] if r.filter in (wp.TIMING_KERNEL, wp.TIMING_KERNEL_BUILTIN) else r.name
        kinds[kind].append(r.elapsed)
        if r.filter in (wp.TIMING_KERNEL, wp.TIMING_KERNEL_BUILTIN):
            kernels[r.name].append(r.elapsed)
    busy = sum(sum(v) for v in kinds.values()) / 1000.0
    print(f"GPU activity: {busy:.3f} s recorded over {wall_s:.2f} s of frames ({busy / max(wall_s, 1e-9):.1%}; "
          f"overlapping activities count once each)")
    print("| activity | count | s | share of wall |")
    print("|---|---|---|---|")
    for kind, v in sorted(kinds.items(), key=lambda kv: -sum(kv[1])):
        print(f"| {kind} | {len(v)} | {sum(v) / 1000:.3f} | {sum(v) / 1000 / wall_s:.1%} |")
    print("| kernel | launches | s | mean us |")
    print("|---|---|---|---|")
    for name, v in sorted(kernels.items(), key=lambda kv: -sum(kv[1]))[:20]:
        print(f"| {name[:90]} | {len(v)} | {sum(v) / 1000:.3f} | {1000 * sum(v) / len(v):.1f} |")


if __name__ == "__main__":
    typer.run(main)
