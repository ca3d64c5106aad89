"""How far a held frictional contact drifts, with friction's sticking stretch carried from step to step and without.

    .venv/bin/python scripts/fem_hold_drift.py [SCENE] [--device cpu|cuda] [--benchmarks]

SCENE (default tests/fixtures/tiny_slide_hold.toml: a sphere with friction 0.5 pressed 1 mm, slid 1 mm, then held
for four frames) must end every indenter's trajectory with a ``hold`` segment. A held indenter does not move, so the
gel should not either. The scene is solved twice on one mesh: as the solver runs by default (friction's memory,
contact.py ``stick_form``) and with ``SolverSettings.friction_memory = False`` (each step's slip measured afresh, the
model before: a sticking point starts every step with no friction traction). Per hold frame and run:
- drift: the largest distance of a marker centre from where it was in the last frame before the hold (mm);
- the tangential force |(Fx, Fy)| and the normal force -Fz of indenter 0 (N);
- Newton iterations.

``--benchmarks`` writes BENCHMARKS.md section ``fem_hold_drift`` (``..._gpu`` where the physics runs on a GPU).
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))
import solver_variants  # noqa: E402
from benchmarks_md import machine_name, update_section  # noqa: E402
from fem_slide_error_vs_runtime import solve  # noqa: E402

from transtac_sim.scene_setup import load_setup  # noqa: E402
from transtac_sim.simulation import physics_device  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def hold_frames(setup) -> int:
    """How many frames every indenter's trajectory ends holding (the scene's frame count is the longest trajectory)."""
    held = []
    for placed in setup.indenters:
        trajectory = placed.config.trajectory
        if not trajectory or trajectory[-1].kind != "hold":
            raise typer.BadParameter(f"indenter {placed.config.name!r} does not end its trajectory with a hold")
        held.append(trajectory[-1].frames)
    return min(held)


def drift(rows: dict, held: int) -> dict:
    """Per hold frame, the largest marker move since the frame before the hold (mm); from the frame before the hold
    on, indenter 0's tangential and normal force (N) and the Newton iterations."""
    markers, forces = np.array(rows["markers"]), np.array(rows["forces"])[:, 0]
    last = len(markers) - held - 1
    return {"drift_mm": np.linalg.norm(markers[last + 1:] - markers[last], axis=2).max(axis=1).tolist(),
            "tangential_n": np.linalg.norm(forces[last:, :2], axis=1).tolist(),
            "normal_n": (-forces[last:, 2]).tolist(), "iterations": rows["iterations"][last:]}


def report(runs: dict, meta: dict) -> str:
    lines = [f"Machine: {meta['machine']}. Command: `{meta['command']}` ({meta['minutes']:.1f} min). Scene: "
             f"`{meta['scene']}`, {meta['frames']} frames, the last {meta['held']} held still, {meta['markers']} "
             "markers. "
             "Hold frame 0 is the frame before the hold; drift is the largest marker move since then.",
             "",
             "| friction's stretch | hold frame | marker drift (mm) | tangential force (N) | normal force (N) "
             "| Newton iterations |",
             "|---|---|---|---|---|---|"]
    for name, r in runs.items():
        for k in range(meta["held"] + 1):
            drift_mm = "-" if k == 0 else f"{r['drift_mm'][k - 1]:.4f}"
            lines.append(f"| {name} | {k} | {drift_mm} | {r['tangential_n'][k]:.4f} | {r['normal_n'][k]:.4f} "
                         f"| {r['iterations'][k]} |")
    return "\n".join(lines)


def main(scene: Path = typer.Argument(ROOT / "tests" / "fixtures" / "tiny_slide_hold.toml"),
         device: str = typer.Option("", help="replace the scene's [physics] device (cpu, cuda)"),
         benchmarks: bool = typer.Option(False, help="write BENCHMARKS.md section fem_hold_drift[_gpu]")) -> None:
    setup = load_setup(scene)
    if not setup.has_contact:
        raise typer.BadParameter(f"{scene}: no indenter touches the gel")
    held = hold_frames(setup)
    if device:
        physics = setup.scene.physics.model_copy(update={"device": device})
        setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    frames = setup.scene.frame_count
    t0 = time.perf_counter()
    runs = {}
    for name, memory in (("carried (default)", True), ("measured afresh (before)", False)):
        solver_variants.solver_settings(friction_memory=memory)
        runs[name] = drift(solve(setup, frames), held)
        print(f"{name}: drift per hold frame {np.round(runs[name]['drift_mm'], 4).tolist()} mm, tangential force "
              f"{np.round(runs[name]['tangential_n'], 4).tolist()} N", flush=True)
    gpu = physics_device(setup.scene.physics.device).startswith("cuda")
    scene_name = scene.resolve().relative_to(ROOT) if scene.resolve().is_relative_to(ROOT) else scene
    meta = {"machine": machine_name("cuda" if gpu else "cpu"), "minutes": (time.perf_counter() - t0) / 60,
            "scene": str(scene_name), "frames": frames, "held": held,
            "markers": len(setup.sensor.markers_rest_gel_mm),
            "command": " ".join([".venv/bin/python scripts/fem_hold_drift.py", *sys.argv[1:]])}
    body = report(runs, meta)
    print(body)
    if benchmarks:
        update_section(ROOT / "BENCHMARKS.md", "fem_hold_drift" + ("_gpu" if gpu else ""), body)


if __name__ == "__main__":
    typer.run(main)
