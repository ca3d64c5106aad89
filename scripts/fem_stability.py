"""Stability sweep of the quasi-static FEM: materials, depths, sharp indenters, friction, bad starts.

Each case presses (and possibly slides) an indenter into a 10 x 10 x 5 mm gel block (graded P2 mesh)
and reports: outcome (converged / clear error), NaN check, min det F over all frames, Newton iterations,
sub-steps and seconds. Writes a markdown table into BENCHMARKS.md (section fem_stability).

    .venv/bin/python scripts/fem_stability.py [--quick] [--device cpu|cuda]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import trimesh
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name as machine  # noqa: E402
from benchmarks_md import update_section

from transtac_sim.physics import (  # noqa: E402
    ElasticMaterial,
    IndenterStartsInsideGel,
    QuasiStaticSolver,
    RigidIndenter,
    SolverDidNotConverge,
    SolverSettings,
)
from transtac_sim.physics.box_mesh import gel_block  # noqa: E402

THICKNESS = 5.0


def indenter(kind: str, friction: float) -> RigidIndenter:
    if kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=4, radius=3.0)
    elif kind == "cube_edge":  # a 4 mm cube turned 45 deg about x: an edge points down
        mesh = trimesh.creation.box(extents=(4.0, 4.0, 4.0))
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 4, [1, 0, 0]))
    else:  # cone, tip down at the local origin's -z side
        mesh = trimesh.creation.cone(radius=3.0, height=4.0, sections=32)
        mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi, [1, 0, 0]))
    return RigidIndenter.from_trimesh(kind, mesh, friction)


def run_case(case: dict, device: str, quick: bool) -> dict:
    h = 0.8 if quick else 0.5
    V, T = gel_block(10.0, 10.0, THICKNESS, h_fine=h, fine_half_width=3.0, growth=1.6)
    materials = [ElasticMaterial(case.get("E", 0.5), case.get("nu", 0.45))]
    material_index = None
    if case.get("backing"):  # bottom 1 mm is a backing 1000x stiffer (two-region mesh)
        materials.append(ElasticMaterial(1000.0 * materials[0].young_mpa, 0.3))
        material_index = (V[T].mean(axis=1)[:, 2] < 1.0).astype(int)
    ind = indenter(case.get("shape", "sphere"), case.get("friction", 0.0))
    solver = QuasiStaticSolver(V, T, materials, [ind], SolverSettings(), device=device, material_index=material_index)
    start = np.eye(4)
    start[2, 3] = THICKNESS - ind.lowest_z(np.eye(4)) + case.get("start_gap", 1e-3)
    depth = case.get("depth", 0.3) * THICKNESS
    frames = 3 if quick else 6
    poses = [start.copy() for _ in range(frames)]
    for k, P in enumerate(poses):
        P[2, 3] -= depth * (k + 1) / frames
    for _ in range(case.get("slide_frames", 0)):
        P = poses[-1].copy()
        P[0, 3] += 0.5
        poses.append(P)
    row = {"outcome": "converged", "nan": False, "min_det": np.inf, "iters": 0, "substeps": 1, "seconds": 0.0}
    t0 = time.perf_counter()
    try:
        solver.start([start])
        for P in poses:
            r = solver.solve_frame([P])
            row["nan"] |= not np.all(np.isfinite(r.displacement_mm))
            row["min_det"] = min(row["min_det"], r.record.min_det_f)
            row["iters"] += r.record.iterations
            row["substeps"] = max(row["substeps"], r.record.substeps)
            row["fz"] = r.forces_n[0, 2]
            row["fx"] = r.forces_n[0, 0]
    except (SolverDidNotConverge, IndenterStartsInsideGel) as e:
        row["outcome"] = f"clear error: {type(e).__name__}: {str(e)[:120]}"
    row["seconds"] = time.perf_counter() - t0
    return row


def cases(quick: bool) -> list[dict]:
    out = [{"name": f"nu={nu}", "nu": nu} for nu in (0.3, 0.45, 0.49, 0.499)]
    out += [{"name": f"E={E} MPa", "E": E} for E in (0.05, 0.5, 5.0)]
    out += [{"name": "gel on 1000x stiffer backing", "backing": True}]
    out += [{"name": f"depth {int(d * 100)} % of thickness", "depth": d} for d in (0.1, 0.3, 0.5)]
    out += [{"name": "cube edge, 30 %", "shape": "cube_edge"}, {"name": "cone tip, 30 %", "shape": "cone"}]
    out += [{"name": f"slide mu={mu}", "friction": mu, "slide_frames": 4, "depth": 0.1} for mu in (0.2, 1.0)]
    out += [{"name": "starts 1 mm inside the gel", "start_gap": -1.0}]
    if quick:
        out = [c for c in out if c["name"] not in ("E=0.5 MPa", "depth 30 % of thickness", "nu=0.45")]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--quick", action="store_true", help="coarser mesh, 3 press frames, fewer cases")
    args = parser.parse_args()
    wp.config.quiet = True
    lines = [
        f"Machine: {machine(args.device)}. Command: `.venv/bin/python scripts/fem_stability.py {' '.join(sys.argv[1:])}`",
        "",
        "| case | outcome | NaN | min det F | Newton iters | max substeps | Fz (N) | s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case in cases(args.quick):
        r = run_case(case, args.device, args.quick)
        line = (f"| {case['name']} | {r['outcome']} | {r['nan']} | {r['min_det']:.3f} | {r['iters']} | "
                f"{r['substeps']} | {r.get('fz', float('nan')):.4g} | {r['seconds']:.1f} |")
        print(line, flush=True)
        lines.append(line)
    update_section(Path("BENCHMARKS.md"), "fem_stability", "\n".join(lines))


if __name__ == "__main__":
    main()
