"""Seconds per quasi-static frame of a press-and-slide scene (sphere R = 3 mm, friction 0.5) on a
20 x 20 x 5 mm gel (graded P2 mesh), at a given fine mesh size. Writes BENCHMARKS.md (section bench_fem).

    .venv/bin/python scripts/bench_fem.py [--device cpu|cuda] [--h-fine 0.5] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import trimesh
import warp as wp

from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter, SolverSettings
from transtac_sim.physics.box_mesh import gel_block

sys.path.insert(0, __file__.rsplit("/", 1)[0])
from benchmarks_md import machine_name as machine  # noqa: E402
from benchmarks_md import update_section  # noqa: E402


def bench(h_fine: float, device: str, frames: int, degree: int = 2) -> dict:
    V, T = gel_block(20.0, 20.0, 5.0, h_fine=h_fine, fine_half_width=3.0, growth=1.5)
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=4, radius=3.0), 0.5)
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [sphere], SolverSettings(degree=degree), device)
    P = np.eye(4)
    P[2, 3] = 5.0 + 3.0 + 1e-3
    solver.start([P])
    poses = []
    for k in range(frames):
        P = P.copy()
        if k < frames // 2:
            P[2, 3] -= 1.0 / (frames // 2)
        else:
            P[0, 3] += 0.25
        poses.append(P)
    solver.solve_frame([poses[0]])  # warm-up (kernel compilation, first factorisation)
    t0 = time.perf_counter()
    iters = 0
    for P in poses[1:]:
        iters += solver.solve_frame([P]).record.iterations
    wall = (time.perf_counter() - t0) / (len(poses) - 1)
    return {"tets": len(T), "dofs": 3 * solver._space.node_count(), "s_per_frame": wall,
            "iters_per_frame": iters / (len(poses) - 1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--h-fine", type=float, default=0.5, help="element size under the contact (mm)")
    parser.add_argument("--quick", action="store_true", help="4 frames instead of 8")
    parser.add_argument("--find-10fps", action="store_true", help="refine h until a frame takes > 0.1 s")
    args = parser.parse_args()
    wp.config.quiet = True
    frames = 4 if args.quick else 8
    r = bench(args.h_fine, args.device, frames)
    lines = [
        f"Machine: {machine(args.device)}. Command: `.venv/bin/python scripts/bench_fem.py {' '.join(sys.argv[1:])}`",
        "",
        "| h fine (mm) | tets | dofs (P2) | s / frame | Newton iters / frame |",
        "|---|---|---|---|---|",
        f"| {args.h_fine} | {r['tets']} | {r['dofs']} | {r['s_per_frame']:.3f} | {r['iters_per_frame']:.1f} |",
    ]
    if args.find_10fps:
        h = args.h_fine
        while r["s_per_frame"] < 0.1 and h > 0.05:
            h *= 0.8
            r = bench(h, args.device, frames)
            lines.append(f"| {h:.3f} | {r['tets']} | {r['dofs']} | {r['s_per_frame']:.3f} | "
                         f"{r['iters_per_frame']:.1f} |")
    print("\n".join(lines))
    update_section(Path(__file__).resolve().parents[1] / "BENCHMARKS.md", "bench_fem" + ("_gpu" if args.device.startswith("cuda") else ""), "\n".join(lines))


if __name__ == "__main__":
    main()
