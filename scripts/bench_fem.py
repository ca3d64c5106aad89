"""Seconds per quasi-static FEM frame, on this CPU or a GPU. Writes BENCHMARKS.md (section bench_fem_cpu or
bench_fem_gpu).

    .venv/bin/python scripts/bench_fem.py [--device cpu|cuda] [--linear-solver auto|direct|cg] [--frames N] [--sweep]

Part 1, the default press-and-slide scene: ``scenes/press_slide.toml`` solved as ``generate`` solves it (its gel
mesh, the default element order and tolerances, its trajectory: a 4 mm sphere with friction 0.5 pressed 1 mm,
slid 2 mm, released), the first ``--frames`` frames; per frame: seconds, Newton iterations, sub-steps.

Part 2 (``--sweep``), the resolution at which the device still solves 10 frames per second: a sphere (R 3 mm,
friction 0.5) pressed 0.6 mm and slid 0.5 mm on a 20 x 20 x 5 mm gel block (graded mesh, element size h
under the sphere), P1 and P2, from coarse to fine h until a frame takes over 1 s. Frames after the first
(kernel compilation, first factorisation) are timed.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name as machine  # noqa: E402
from benchmarks_md import update_section  # noqa: E402

from transtac_sim.dataset.sequence import StageClock  # noqa: E402
from transtac_sim.meshing import mesh_gel  # noqa: E402
from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter, SolverSettings  # noqa: E402
from transtac_sim.physics.box_mesh import gel_block  # noqa: E402
from transtac_sim.scene_setup import load_setup  # noqa: E402
from transtac_sim.simulation import simulate_frames  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SWEEP_H_MM = (2.5, 1.8, 1.3, 1.0, 0.75, 0.55, 0.4)


def scene_frames(device: str, linear_solver: str, frames: int) -> list[str]:
    setup = load_setup(ROOT / "scenes" / "press_slide.toml")
    physics = setup.scene.physics.model_copy(update={"device": device, "linear_solver": linear_solver})
    setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    clock = StageClock()
    rows = []
    for f in simulate_frames(setup, frames, clock):
        s = f.solver
        rows.append(f"| {f.frame} | {s['seconds']:.2f} | {s['iterations']} | {s['substeps']} | "
                    f"{-f.forces_n[0][2]:.4f} |")
        print(rows[-1], flush=True)
    tets = len(mesh_gel(setup).mesh.tets)  # cached: the mesh simulate_frames used
    seconds = [float(r.split("|")[2]) for r in rows]
    head = [
        f"Default press-and-slide scene (`scenes/press_slide.toml`, {tets} tets, P{physics.degree}, "
        f"newton_tol {physics.newton_tol_mm} mm, {linear_solver} linear solver): mean {np.mean(seconds):.2f} s per frame, "
        f"{np.mean(seconds[1:] or seconds):.2f} s without the first (kernel compilation). Mesh set-up "
        f"{clock.seconds.get('physics_setup', 0.0):.1f} s.",
        "",
        "| frame | s | Newton iterations | sub-steps | indenter force -Fz (N) |",
        "|---|---|---|---|---|",
    ]
    return head + rows


def block_frame_seconds(h: float, degree: int, device: str, linear_solver: str) -> dict:
    V, T = gel_block(20.0, 20.0, 5.0, h_fine=h, fine_half_width=3.0, growth=1.5)
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=4, radius=3.0), 0.5)
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [sphere], SolverSettings(
        degree=degree, newton_tol_mm=1e-4, linear_solver=linear_solver), device)
    P = np.eye(4)
    P[2, 3] = 5.0 + 3.0 + 1e-3
    solver.start([P])
    poses = []
    for k in range(5):
        P = P.copy()
        if k < 3:
            P[2, 3] -= 0.2
        else:
            P[0, 3] += 0.25
        poses.append(P)
    solver.solve_frame([poses[0]])  # warm-up: kernel compilation, first factorisation
    t0 = time.perf_counter()
    iters = sum(solver.solve_frame([P]).record.iterations for P in poses[1:])
    return {"tets": len(T), "dofs": 3 * solver._space.node_count(),
            "s": (time.perf_counter() - t0) / (len(poses) - 1), "iters": iters / (len(poses) - 1)}


def sweep(device: str, linear_solver: str) -> list[str]:
    rows = ["| order | h under the sphere (mm) | tets | dofs | s / frame | Newton iterations / frame | >= 10 frames/s |",
            "|---|---|---|---|---|---|---|"]
    finest = {}
    for degree in (1, 2):
        for h in SWEEP_H_MM:
            r = block_frame_seconds(h, degree, device, linear_solver)
            fast = r["s"] <= 0.1
            if fast:
                finest[degree] = (h, r["dofs"])
            rows.append(f"| P{degree} | {h} | {r['tets']} | {r['dofs']} | {r['s']:.3f} | {r['iters']:.1f} | "
                        f"{'yes' if fast else 'no'} |")
            print(rows[-1], flush=True)
            if r["s"] > 1.0:
                break
    verdict = "; ".join(f"P{d}: finest h {h} mm ({n} dofs)" for d, (h, n) in finest.items()) or (
        "no resolution tried reaches 10 frames per second")
    return [f"Resolution sweep (20 x 20 x 5 mm block, sphere R 3 mm, friction 0.5, {linear_solver} linear solver). 10 frames/s: {verdict}.", "",
            *rows]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--linear-solver", choices=("auto", "direct", "cg"), default="auto",
                        help="auto: cg on a GPU, direct on the CPU")
    parser.add_argument("--frames", type=int, default=10, help="frames of the press-and-slide scene (0: skip)")
    parser.add_argument("--sweep", action="store_true", help="also the resolution sweep (10 frames/s)")
    parser.add_argument("--out-md", type=Path, default=ROOT / "BENCHMARKS.md")
    args = parser.parse_args()
    lines = [f"Machine: {machine(args.device)}. Command: `.venv/bin/python scripts/bench_fem.py "
             f"{' '.join(sys.argv[1:])}`", ""]
    if args.frames:
        lines += scene_frames(args.device, args.linear_solver, args.frames) + [""]
    if args.sweep:
        lines += sweep(args.device, args.linear_solver)
    print("\n".join(lines))
    section = ("bench_fem_gpu" if args.device.startswith("cuda") else "bench_fem_cpu") + (
        f"_{args.linear_solver}" if args.linear_solver != "auto" else "")
    update_section(args.out_md, section, "\n".join(lines))


if __name__ == "__main__":
    main()
