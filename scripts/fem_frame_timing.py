"""Seconds, Newton iterations and forces per FEM frame of a scene, as `generate` would solve it.

    .venv/bin/python scripts/fem_frame_timing.py tests/fixtures/tiny_press.toml [--degree 2] [--frames 2]
    .venv/bin/python scripts/fem_frame_timing.py tests/fixtures/tiny_press.toml --trajectory-from \
        scenes/press_slide.toml --frames 8

``--trajectory-from SCENE`` replaces the indenters' trajectories and friction by those of SCENE's indenters
(same order): the press-and-slide motion on the tiny scene's mesh. Per frame it prints the solver record:
Newton iterations (Hessian assemblies), line-search halvings, contact stiffness raises, warm starts,
sub-steps, seconds, the residual and what friction's lag leaves unbalanced (``SolverRecord.friction_lag_residual_n``).

``--friction MU`` replaces every indenter's friction coefficient (0: frictionless), e.g. to see what friction costs.
``--newton-force-rtol R`` replaces the scene's ``[physics] newton_force_rtol`` (Newton's force test, 3e-3 unless a scene
sets it; 0: the step-length test alone).
``--no-friction-memory`` measures each step's slip afresh (``SolverSettings.friction_memory``, the friction model before
contact.py carried its sticking stretch from step to step).

``--sequence I`` solves sequence I of a randomised scene (its drawn indenter, depth, slide, friction and
layout, as ``generate`` would): e.g. to see why a frame of ``scenes/train_random.toml`` failed.

``--warm-start``, ``--exact-below``, ``--lag-move-ratio`` and ``--press-lag-move-ratio`` switch on the Newton variants
of scripts/solver_variants.py (BENCHMARKS.md ``fem_slide_iterations_gpu``, ``fem_press_lag_moves_gpu``).

``--label NAME --benchmarks`` stores the run under NAME in BENCHMARKS.md's ``fem_newton_iterations_cpu``
section (the runs are kept in the section itself, so that "before" and "after" runs of different code
versions sit in one table) and rewrites its table: median and per-frame iterations and seconds.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
import statistics
import time
from pathlib import Path

import solver_variants
import typer

from transtac_sim.config import load_scene
from transtac_sim.dataset.sequence import StageClock
from transtac_sim.physics import QuasiStaticSolver
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import physics_device, simulate_frames

SECTION = "fem_newton_iterations_cpu"
BENCHMARKS = Path(__file__).resolve().parents[1] / "BENCHMARKS.md"


def _with_trajectories(setup, source: Path):
    others = load_scene(source).indenters
    if len(others) != len(setup.indenters):
        raise typer.BadParameter(f"{source} has {len(others)} indenter(s), the scene {len(setup.indenters)}")
    placed = [dataclasses.replace(p, config=p.config.model_copy(update={"trajectory": o.trajectory,
                                                                         "friction": o.friction}))
              for p, o in zip(setup.indenters, others, strict=True)]
    return dataclasses.replace(setup, indenters=type(setup.indenters)(placed))


def _sequence_setup(scene: Path, index: int):
    from transtac_sim.dataset.sequence import sequence_setup

    setup, variant = sequence_setup(load_scene(scene), scene.resolve(), index)
    for ind in variant.scene.indenters:
        print(f"sequence {index}: indenter {ind.mesh}, friction {ind.friction}, gel E "
              f"{setup.sensor.gel.youngs_modulus_mpa} MPa, trajectory "
              f"{[t.model_dump(exclude_defaults=True) for t in ind.trajectory]}")
    return setup


def with_friction(setup, friction: float):
    """The scene setup with every indenter's friction coefficient replaced by ``friction``."""
    placed = [dataclasses.replace(p, config=p.config.model_copy(update={"friction": friction})) for p in setup.indenters]
    return dataclasses.replace(setup, indenters=type(setup.indenters)(placed))


def run(scene: Path, degree: int, frames: int, trajectory_from: Path | None, sequence: int | None = None,
        friction_lag_moves: int | None = None, friction: float | None = None,
        newton_force_rtol: float | None = None) -> dict:
    """Solves the frames; returns the run's description, per-frame solver records, forces (N) and markers (gel frame,
    mm). ``newton_force_rtol`` replaces the scene's [physics] newton_force_rtol (0: the step-length test alone)."""
    setup = load_setup(scene) if sequence is None else _sequence_setup(scene, sequence)
    physics = setup.scene.physics.model_copy(update={"degree": degree} | (
        {"friction_lag_moves": friction_lag_moves} if friction_lag_moves is not None else {}) | (
        {"newton_force_rtol": newton_force_rtol} if newton_force_rtol is not None else {}))
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    if trajectory_from is not None:
        setup = _with_trajectories(setup, trajectory_from)
    if friction is not None:
        setup = with_friction(setup, friction)
    records = []
    solve_frame = QuasiStaticSolver.solve_frame

    def recording(self, poses):  # the full SolverRecord (simulate_frames passes on only part of it)
        result = solve_frame(self, poses)
        records.append(dataclasses.asdict(result.record) | {"stiffness": self.contact_stiffness})
        return result

    QuasiStaticSolver.solve_frame = recording
    what = f"{scene}" + (f" with the trajectories of {trajectory_from}" if trajectory_from else "") + (
        f" sequence {sequence}" if sequence is not None else "") + (f", friction {friction:g}" if friction is not None
                                                                     else "") + (
        f", newton_force_rtol {newton_force_rtol:g}" if newton_force_rtol is not None else "")
    device = physics_device(setup.scene.physics.device)
    print(f"{what} on a {os.cpu_count()}-core CPU (physics device {device}), P{degree}, {frames} frame(s)")
    clock, t0, load0 = StageClock(), time.perf_counter(), os.getloadavg()[0]
    forces, markers = [], []
    try:
        for f in simulate_frames(setup, frames, clock):
            forces.append([x.tolist() for x in f.forces_n])
            markers.append(f.markers_gel_mm)
            r = records[-1] if records else {}
            print(f"frame {f.frame}: {f.solver['seconds']:.1f} s, {f.solver['iterations']} Newton iterations, "
                  f"{r.get('backtracks', '-')} line-search halvings, {r.get('stiffness_raises', '-')} stiffness raises, "
                  f"{r.get('warm_starts', '-')} warm starts, {r.get('lag_updates', '-')} lag moves, {f.solver['substeps']} "
                  f"sub-step(s), residual "
                  f"{f.solver['residual']:.2e} N (lag at the solution: {f.solver['friction_lag_residual_n']:.2e} N), "
                  f"min det F {f.solver['min_det_f']:.3f}, forces "
                  f"{[x.round(4).tolist() for x in f.forces_n]} N (wall {time.perf_counter() - t0:.1f} s)", flush=True)
    finally:
        QuasiStaticSolver.solve_frame = solve_frame
    print({k: round(v, 2) for k, v in clock.seconds.items()})
    return {"scene": what, "device": device, "degree": degree, "frames": frames, "load_average": [load0, os.getloadavg()[0]],
            "iterations": [r["iterations"] for r in records], "seconds": [round(r["seconds"], 2) for r in records],
            "backtracks": [r.get("backtracks") for r in records], "lag_moves": [r.get("lag_updates") for r in records],
            "lag_residual_n": [r.get("friction_lag_residual_n") for r in records],
            "forces_n": forces, "markers_mm": markers}


def _stored_runs() -> dict:
    text = BENCHMARKS.read_text() if BENCHMARKS.exists() else ""
    m = re.search(rf"<!-- BEGIN {SECTION} -->.*?<!-- runs: (.*?) -->", text, flags=re.S)
    return json.loads(m.group(1)) if m else {}


def _listed(values) -> str:
    """Per-frame counts, or "-" where the solver of that run did not record them."""
    return ", ".join(map(str, values)) if values and None not in values else "-"


def _markdown(runs: dict) -> str:
    from benchmarks_md import machine_name

    lines = [f"Machine: {machine_name()}, shared (load average at the start and end of each run in the table; "
             "seconds vary with it, iterations do not). P2, CHOLMOD (`linear_solver = \"auto\"` on the CPU).",
             "Command: `.venv/bin/python scripts/fem_frame_timing.py tests/fixtures/tiny_press.toml --label L "
             "--benchmarks` and the same with `--trajectory-from scenes/press_slide.toml --frames 8` (the "
             "press-and-slide motion, friction 0.5, on the tiny mesh). `before`: the same commands with "
             "`PYTHONPATH` pointing at a checkout of commit 0310f2c (its `transtac_sim`, the solver before issue 12 "
             "item 1); `after`: this tree. Iterations count Hessian assemblies (the earlier solver's included one "
             "per Newton solve that only confirmed convergence). Forces agree within 0.2 % on the press frames "
             "and 0.7 % (friction force) on the slide frames.",
             "",
             "| run | scene | frames | Newton iterations per frame (median) | per frame | s per frame (median) "
             "| per frame | line-search halvings per frame | friction lag moves per frame | load |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for key, r in runs.items():
        label, _, _ = key.partition("|")
        lines.append(f"| {label} | {r['scene']} | {r['frames']} | {statistics.median(r['iterations']):g} | "
                     f"{', '.join(map(str, r['iterations']))} | {statistics.median(r['seconds']):.1f} | "
                     f"{', '.join(f'{s:.1f}' for s in r['seconds'])} | {_listed(r.get('backtracks'))} | "
                     f"{_listed(r.get('lag_moves'))} | "
                     f"{r['load_average'][0]:.1f}-{r['load_average'][1]:.1f} |")
    return "\n".join(lines) + f"\n\n<!-- runs: {json.dumps(runs)} -->"


def main(scene: Path, degree: int = typer.Option(2, min=1, max=2), frames: int = typer.Option(2, min=1),
         trajectory_from: Path | None = typer.Option(None, help="take the indenters' trajectories and friction "
                                                                  "from this scene"),
         label: str = typer.Option("", help="name of this run in the BENCHMARKS.md table"),
         benchmarks: bool = typer.Option(False, help=f"store the run in BENCHMARKS.md's {SECTION} section"),
         sequence: int | None = typer.Option(None, min=0, help="solve this sequence of a randomised scene"),
         max_newton_iterations: int | None = typer.Option(None, min=1, help="replace SolverSettings' "
                                                          "max_newton_iterations (per sub-step)"),
         friction_lag_moves: int | None = solver_variants.FRICTION_LAG_MOVES_OPTION,
         friction: float | None = typer.Option(None, min=0.0, help="replace every indenter's friction coefficient "
                                               "(after --trajectory-from)"),
         newton_force_rtol: float | None = typer.Option(None, min=0.0, max=0.1, help="replace the scene's [physics] "
                                                        "newton_force_rtol (Newton's force test; 0: off)"),
         warm_start: str = solver_variants.WARM_START_OPTION,
         exact_below: float = solver_variants.EXACT_BELOW_OPTION,
         lag_move_ratio: float | None = solver_variants.LAG_MOVE_RATIO_OPTION,
         press_lag_move_ratio: float | None = solver_variants.PRESS_LAG_MOVE_RATIO_OPTION,
         contact_prediction: bool = solver_variants.CONTACT_PREDICTION_OPTION,
         estimate_rtol: float = solver_variants.ESTIMATE_RTOL_OPTION,
         estimate_cap_factor: float = solver_variants.ESTIMATE_CAP_FACTOR_OPTION,
         estimate_band: str | None = solver_variants.ESTIMATE_BAND_OPTION,
         friction_memory: bool = solver_variants.FRICTION_MEMORY_OPTION) -> None:
    solver_variants.apply(warm_start, exact_below, lag_move_ratio, estimate_rtol, estimate_cap_factor, estimate_band,
                          press_lag_move_ratio, contact_prediction)
    solver_variants.solver_settings(friction_memory=friction_memory, **(
        {"max_newton_iterations": max_newton_iterations} if max_newton_iterations is not None else {}))
    if not friction_memory:
        print("friction's sticking stretch is not carried from step to step (--no-friction-memory)")
    result = run(scene, degree, frames, trajectory_from, sequence, friction_lag_moves, friction, newton_force_rtol)
    if benchmarks:
        from benchmarks_md import update_section

        runs = _stored_runs()
        runs[f"{label or 'run'}|{result['scene']}"] = {k: v for k, v in result.items()
                                                        if k not in ("forces_n", "markers_mm")}
        update_section(BENCHMARKS, SECTION, _markdown(runs))
        print(f"BENCHMARKS.md: {SECTION} updated")


if __name__ == "__main__":
    typer.run(main)
