"""One sequence of a scene, frame by frame, with the solver record of each frame, and the Python stack on demand: to
find where a sequence that will not finish spends its time.

    .venv/bin/python scripts/trace_sequence.py scenes/train_random.toml --sequence 17 --frames 3 \
        [--mode physics|worker] [--linear-solver auto|direct|cg]

``--mode physics`` solves the frames as ``simulate_frames`` does (what ``fem_frame_timing.py`` times); ``--mode worker``
runs the sequence as one ``generate`` worker does (physics, render, labels, write into a temporary dataset folder),
in this process. Each load sub-step prints its seconds, Newton iterations, outcome and the frame's counters so far;
each frame its seconds, Newton iterations, sub-steps, residual (N) and Fz (N); each device CG that stops unconverged
its reason, and each host solve its seconds; with ``--newton``, each Newton system (which Hessian, its outcome, its
linear iterations) and at the end a table of where each frame's Newton iterations went: before friction's first lag
move (of which on the clamped or Gauss-Newton Hessian, where the exact one was not positive definite) and after it;
``--warm-start-distance`` prints, after each load sub-step, how far its start and each warm-start guess
(warm_start.py ``_guesses``, in the order made) lay from the solution Newton reached: the 90th and 99th percentile
and the largest distance over the nodes (mm); ``--warm-start`` picks the guesses (scripts/solver_variants.py).
``--curvature`` (device path): where the device CG finds the exact Hessian of a Newton system not positive definite,
the curvature p . H p / |p|^2 (N/mm) of the CG direction p where it stopped (p . A p <= 0, A the matrix rounded to
float32; a stop at r . M r <= 0 is only reported), in float64 with the exact, the clamped and the Gauss-Newton
Hessian (elasticity.py), and where p lies: the share of |p|^2 on its 10 largest nodes, and those nodes' depth below
the top surface and distance from the first indenter's axis at the sub-step's target pose (mm). Both print the
frame's index.
``kill -USR1 <pid>`` prints the main thread's Python stack to stderr (``faulthandler``; its periodic dump from a
watchdog thread crashed this process in libpython twice, so it is not used). The gel mesh comes from the
mesh cache (``TRANSTAC_SIM_CACHE``): a mesh built anew elsewhere differs, and so do the frames (README, Determinism).
"""

from __future__ import annotations

import faulthandler
import json
import signal
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import solver_variants
import typer
import warp as wp
from warp.sparse import bsr_mv

from transtac_sim.config import load_scene
from transtac_sim.physics import QuasiStaticSolver, cg_kernels, device_linear, linear
from transtac_sim.physics.device_linear import DeviceSolves
from transtac_sim.physics.elasticity import CLAMPED, EXACT
from transtac_sim.physics.warm_start import WarmStart

HESSIANS = {(1.0, EXACT): "exact", (1.0, CLAMPED): "clamped", (0.0, CLAMPED): "Gauss-Newton"}


def _new_frame_counts() -> dict:
    return {"steps": 0, "before_lag": 0, "clamped_before_lag": 0, "after_lag": 0, "lag_moves": 0}


#: Newton steps per frame (``--newton``): the frames done, then the one being solved
ANATOMY: list[dict] = [_new_frame_counts()]


def anatomy_table(frames: list[dict]) -> str:
    """Markdown table of ``ANATOMY``'s finished frames, with the sums over frames 1 on (frame 0 is the first touch)."""
    keys = ("steps", "before_lag", "clamped_before_lag", "after_lag", "lag_moves")
    rows = ["| frame | Newton steps | before friction's first lag move | of those, clamped or Gauss-Newton Hessian "
            "| after it | lag moves |", "|---|---|---|---|---|---|"]
    rows += [f"| {k} | " + " | ".join(str(f[key]) for key in keys) + " |" for k, f in enumerate(frames)]
    if len(frames) > 1:
        rows.append(f"| 1-{len(frames) - 1} | " + " | ".join(str(sum(f[key] for f in frames[1:])) for key in keys)
                    + " |")
    return "\n".join(rows)


def _trace_newton() -> None:
    """Prints each Newton system as it is solved: which Hessian (newton.py ``_hessian_ladder``), what came of it (a
    step, not positive definite, or a shifted step) and the linear iterations it took."""
    hessian, solve = QuasiStaticSolver._hessian, linear.LinearSolver.solve
    last = {}

    def logged_hessian(self, ind, geometric, clamp=True):
        last["which"] = HESSIANS.get((geometric, clamp), f"geometric {geometric}, clamp {clamp}")
        return hessian(self, ind, geometric, clamp)

    def logged_solve(self, H, rhs, definite=False, **kwargs):
        du = solve(self, H, rhs, definite, **kwargs)
        outcome = "not positive definite" if du is None else (f"shifted {self.last_shift:g}" if self.last_shift
                                                                 else "step")
        step = f", max |du| {float(np.max(np.abs(du.numpy()))):.2e} mm" if du is not None else ""
        if du is not None:
            counts = ANATOMY[-1]
            counts["steps"] += 1
            if counts["lag_moves"] == 0:
                counts["before_lag"] += 1
                counts["clamped_before_lag"] += last.get("which") != "exact"
            else:
                counts["after_lag"] += 1
        print(f"    Newton system, {last.get('which')} Hessian: {outcome}{step}, |g| {np.linalg.norm(rhs.numpy()):.2e} N, "
              f"{self.last_iterations} linear iterations, rtol {kwargs.get('rtol', 0.0):.1e}, refined to "
              f"{kwargs.get('tight') or self.cg_tol:.1e}", flush=True)
        return du

    move_lag, raise_stiffness = QuasiStaticSolver._move_lag, QuasiStaticSolver._raise_stiffness

    def logged_move_lag(self, ind, remaining, *args):
        moved = move_lag(self, ind, remaining, *args)
        if moved:
            ANATOMY[-1]["lag_moves"] += 1
            print(f"    friction's lag moved (estimated remaining step {remaining:.2e} mm)", flush=True)
        return moved

    def logged_raise(self, ind, raises):
        pen = raise_stiffness(self, ind, raises)
        print(f"    converged at penetration {pen:.3g} mm" if pen is not None else
              f"    contact stiffness raised to {self.contact_stiffness:.4g} N/mm^3", flush=True)
        return pen

    QuasiStaticSolver._hessian = logged_hessian
    QuasiStaticSolver._move_lag = logged_move_lag
    QuasiStaticSolver._raise_stiffness = logged_raise
    linear.LinearSolver.solve = logged_solve


def _trace_warm_start() -> None:
    """Keeps each sub-step's warm-start guesses and start, and prints their distances from the sub-step's solution."""
    guesses, start, solve_step = WarmStart._guesses, WarmStart._warm_start, QuasiStaticSolver._solve_step
    kept = {}

    def kept_guesses(self, step):
        for guess in guesses(self, step):
            kept["guesses"].append(np.array(guess.numpy()))  # a copy: on the CPU .numpy() is a view
            yield guess

    def kept_start(self, ind, step):
        kept.update(guesses=[], prev=np.array(self.u_prev.dof_values.numpy()))
        taken = start(self, ind, step)
        kept["start"] = np.array(self.u.dof_values.numpy())
        return taken

    def distances(self, poses, *args, **kwargs):
        kept.clear()
        result = solve_step(self, poses, *args, **kwargs)
        if "start" in kept and result[0]:
            u = self.u.dof_values.numpy()

            def far(v):
                d = np.linalg.norm(v - u, axis=1)
                return f"{np.quantile(d, 0.9):.3f} / {np.quantile(d, 0.99):.3f} / {d.max():.3f}"

            print(f"    frame {self.frame_index}, from the solution (mm, nodes' 90th / 99th percentile / "
                  f"largest): last state {far(kept['prev'])}, start {far(kept['start'])}, guesses "
                  + ", ".join(far(g) for g in kept["guesses"]), flush=True)
        return result

    WarmStart._guesses = kept_guesses
    WarmStart._warm_start = kept_start
    QuasiStaticSolver._solve_step = distances


def _trace_curvature() -> None:
    """Prints the curvature of the device CG's direction where it stops on the exact Hessian (``--curvature``)."""
    hessian, solve_cg, cg = QuasiStaticSolver._hessian, DeviceSolves._solve_cg, device_linear.definite_cg
    solve_step = QuasiStaticSolver._solve_step
    last = {}

    def kept_pose(self, poses, *args, **kwargs):  # the sub-step's target poses (self.poses moves at the frame's end)
        last["axis"] = np.asarray(poses[0])[:2, 3]
        return solve_step(self, poses, *args, **kwargs)

    def kept_hessian(self, ind, geometric, clamp=CLAMPED):
        last.update(solver=self, ind=ind, exact=(geometric, clamp) == (1.0, EXACT))
        return hessian(self, ind, geometric, clamp)

    def kept_matrix(self, H, *args, **kwargs):  # a Newton system's solve (the step estimate's CG is not one)
        last["H"] = H
        try:
            return solve_cg(self, H, *args, **kwargs)
        finally:
            del last["H"]

    def curvature(H, p: wp.array, P: np.ndarray) -> float:
        Hp = wp.zeros_like(p)
        bsr_mv(H, p, Hp, alpha=1.0, beta=0.0)
        return float((P * Hp.numpy()).sum() / (P * P).sum())

    def measured_cg(A, b, x, rtol, maxiter, M=None, atol=0.0, workspace=None, coarse=None, **taken):
        result = cg(A, b, x, rtol, maxiter, M, atol, workspace, coarse, **taken)
        if result.not_definite and last.get("exact") and "H" in last and workspace is not None:
            solver, p = last["solver"], workspace.p
            P = p.numpy()
            if workspace.state.numpy()[cg_kernels.STOP] != cg_kernels.NOT_DEFINITE.value:  # at r . M r <= 0
                print(f"    frame {solver.frame_index}: CG stopped where its preconditioner is not positive definite",
                      flush=True)
                return result
            values = {"exact": curvature(last["H"], p, P)}
            for name, geometric in (("clamped", 1.0), ("Gauss-Newton", 0.0)):  # the next rungs assemble anew anyway
                values[name] = curvature(hessian(solver, last["ind"], geometric, CLAMPED), p, P)
            n2 = (P * P).sum(axis=1)
            top = np.argsort(-n2)[:10]
            nodes = solver._node_positions.numpy()
            X = nodes[top]
            axis = last["axis"]
            print(f"    frame {solver.frame_index}, p . H p / |p|^2 (N/mm) where CG stopped after {result.iterations} "
                  "iterations: "
                  + ", ".join(f"{k} {v:.3g}" for k, v in values.items())
                  + f"; its 10 largest nodes carry {n2[top].sum() / n2.sum():.0%} of |p|^2, at depth "
                  f"{np.round(nodes[:, 2].max() - X[:, 2], 2).tolist()} mm, "
                  f"{np.round(np.linalg.norm(X[:, :2] - axis, axis=1), 2).tolist()} mm from the indenter's axis at "
                  f"({axis[0]:.3f}, {axis[1]:.3f}) mm",
                  flush=True)
        return result

    QuasiStaticSolver._hessian = kept_hessian
    QuasiStaticSolver._solve_step = kept_pose
    DeviceSolves._solve_cg = kept_matrix
    device_linear.definite_cg = measured_cg


def _trace_solver() -> None:
    """Prints, as they happen: each frame, each load sub-step, each device CG that stopped without converging (why,
    after how many iterations) and each host (direct) solve with its seconds."""
    solve_frame, solve_step = QuasiStaticSolver.solve_frame, QuasiStaticSolver._solve_step
    cg, solve_direct = device_linear.definite_cg, linear.LinearSolver._solve_direct

    def logged(self, poses):
        t0 = time.perf_counter()
        result = solve_frame(self, poses)
        r = result.record
        print(f"frame {self.frame_index - 1}: {time.perf_counter() - t0:.1f} s, {r.iterations} Newton iterations, "
              f"{r.substeps} sub-step(s), residual {r.residual:.2e} N, Fz {result.forces_n[0][2]:.4f} N, "
              f"{self._linear.shifted_solves} shifted device solves so far, "
              f"{self._linear.float64_solves} solved with the float64 product", flush=True)
        ANATOMY.append(_new_frame_counts())
        return result

    def logged_step(self, poses, *args, **kwargs):
        t0 = time.perf_counter()
        ok, iterations, why, pen = solve_step(self, poses, *args, **kwargs)
        print(f"  sub-step to z {poses[0][2, 3]:.4f} mm: {time.perf_counter() - t0:.1f} s, {iterations} Newton "
              f"iterations, {'converged' if ok else 'failed: ' + why}, penetration {pen:.3g} mm, "
              f"{dict(self.stats)}", flush=True)
        return ok, iterations, why, pen

    def logged_cg(A, b, x, rtol, maxiter, *args, **kwargs):
        result = cg(A, b, x, rtol, maxiter, *args, **kwargs)
        if not result.converged:
            print(f"    device CG stopped ({'not positive definite' if result.not_definite else 'iteration cap'}) "
                  f"after {result.iterations} of {maxiter} iterations, rtol {rtol:.1e}", flush=True)
        return result

    def logged_direct(self, *args, **kwargs):
        t0 = time.perf_counter()
        x = solve_direct(self, *args, **kwargs)
        print(f"    host solve of {len(self._free)} dofs: {time.perf_counter() - t0:.1f} s, {self.factorisations} "
              f"factorisation(s) so far", flush=True)
        return x

    QuasiStaticSolver.solve_frame = logged
    QuasiStaticSolver._solve_step = logged_step
    device_linear.definite_cg = logged_cg
    linear.LinearSolver._solve_direct = logged_direct


def main(scene: Path, sequence: int = typer.Option(0, min=0), frames: int = typer.Option(3, min=1),
         mode: str = typer.Option("physics", help="physics or worker"),
         linear_solver: str = typer.Option("auto", help="auto, direct or cg"),
         newton: bool = typer.Option(False, help="also print each Newton system (its Hessian and outcome), and at the "
                                     "end where each frame's Newton steps went"),
         friction_lag_moves: int | None = typer.Option(None, min=1, help="replace [physics] friction_lag_moves"),
         warm_start_distance: bool = typer.Option(False, help="print how far each sub-step's start and warm-start "
                                                  "guesses lay from its solution"),
         warm_start: str = solver_variants.WARM_START_OPTION,
         contact_prediction: bool = solver_variants.CONTACT_PREDICTION_OPTION,
         curvature: bool = typer.Option(False, help="where the device CG finds the exact Hessian not positive "
                                        "definite, print its direction's curvature and where it lies")) -> None:
    if mode not in ("physics", "worker"):
        raise typer.BadParameter(f"--mode must be physics or worker, got {mode!r}")
    faulthandler.register(signal.SIGUSR1, file=sys.stderr, all_threads=False)
    solver_variants.apply(warm_start, contact_prediction=contact_prediction)
    if warm_start_distance:
        _trace_warm_start()
    if curvature:  # before --newton's wrappers, which would otherwise label the refused system by its extra Hessians
        _trace_curvature()
    _trace_solver()
    if newton:
        _trace_newton()
    path = scene.resolve()
    loaded = load_scene(path)
    physics = {"linear_solver": linear_solver}
    if friction_lag_moves is not None:
        physics["friction_lag_moves"] = friction_lag_moves
    loaded = loaded.model_copy(update={"physics": loaded.physics.model_copy(update=physics)})
    if mode == "physics":
        from transtac_sim.dataset.sequence import StageClock, sequence_setup
        from transtac_sim.simulation import simulate_frames

        setup, _ = sequence_setup(loaded, path, sequence)
        for _ in simulate_frames(setup, frames, StageClock()):
            pass
        if newton:
            print(anatomy_table(ANATOMY[:-1]))
        return
    from transtac_sim.dataset.generate import SequenceTask, _run_task
    from transtac_sim.scene_setup import build_setup
    from transtac_sim.writer.atomic import write_json

    resolved = json.loads(loaded.model_dump_json())
    resolved["frames_per_sequence"] = frames
    with tempfile.TemporaryDirectory() as root:
        write_json(Path(root) / "calibration.json", build_setup(loaded, path).sensor.calibration_json())
        for record in _run_task(SequenceTask(str(path), json.dumps(resolved), sequence, root)):
            print(f"frame {record['frame']}: {record['status']}" + (f" ({record['reason']})" if "reason" in record
                                                                      else ""), flush=True)


if __name__ == "__main__":
    typer.run(main)
