"""Where a scene's smallest det F sits, frame by frame: at a check point of which tet, and what that tet's volume does.

    .venv/bin/python scripts/fem_det_f_sites.py scenes/press_slide.toml --frames 8 [--device cpu|cuda]

The solver record's ``min_det_f`` is the smallest det F = J at the inversion barrier's 4 check points per tet
(elasticity.py; the line search rejects any step that makes one <= 0). The volumetric term holds J at one point per
tet, the centroid (P2-P0): there J stays near 1 for a gel of Poisson ratio 0.49, while between that point and a tet's
corners J varies with the quadratic displacement, held by the shear term alone. This script tells the two apart. Per
frame: the smallest check-point J and, for the tet that holds it, its 4 check-point values, its centroid J, its depth
(its rest centroid below the gel's top face, mm), how many of its vertices lie on the boundary and its shape quality
(6 sqrt(2) V / l_rms^3: 1 for a regular tet) with the fraction of tets of worse quality; over the whole mesh, the
range of the centroid J and the number of tets with a check-point J below 0.5.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import typer
import warp as wp
import warp.fem as fem

from transtac_sim.dataset.sequence import StageClock
from transtac_sim.physics import QuasiStaticSolver, elasticity
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import physics_device, simulate_frames


def tet_quality(vertices_mm: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """6 sqrt(2) V / l_rms^3 per tet (V its volume, l_rms the root mean square of its 6 edge lengths): 1 for a
    regular tet, towards 0 for a flat one."""
    c = vertices_mm[tets]
    volume = np.abs(np.linalg.det(c[:, 1:] - c[:, :1])) / 6.0
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    l2 = np.stack([np.sum((c[:, a] - c[:, b]) ** 2, axis=1) for a, b in edges], axis=1).mean(axis=1)
    return 6.0 * np.sqrt(2.0) * volume / l2 ** 1.5


def boundary_vertices(tets: np.ndarray) -> np.ndarray:
    """Boolean per vertex: on a face that only one tet has."""
    faces = np.sort(tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    unique, counts = np.unique(faces, axis=0, return_counts=True)
    on = np.zeros(int(tets.max()) + 1, dtype=bool)
    on[unique[counts == 1].ravel()] = True
    return on


def det_f_fields(solver: QuasiStaticSolver) -> tuple[np.ndarray, np.ndarray]:
    """(J at the 4 check points of each tet, shape (T, 4); J at each tet's centroid, shape (T,)) at the solver's
    current displacement."""
    n_tets = len(solver.tets)
    check = wp.empty(solver._q_det.total_point_count(), dtype=wp.float64, device=solver.device)
    fem.interpolate(elasticity.det_form, dest=check, at=solver._q_det, fields={"u": solver.u})
    centroid = wp.empty(n_tets, dtype=wp.float64, device=solver.device)
    fem.interpolate(elasticity.det_form, dest=centroid, at=solver._q_vol, fields={"u": solver.u})
    return check.numpy().reshape(n_tets, -1), centroid.numpy()


def frame_row(frame: int, iterations: int, check: np.ndarray, centroid: np.ndarray, quality: np.ndarray,
              on_boundary: np.ndarray, vertices_mm: np.ndarray, tets: np.ndarray, top_mm: float) -> str:
    """One markdown row of the table (``main``'s header)."""
    t = int(np.argmin(check.min(axis=1)))
    depth = top_mm - float(vertices_mm[tets[t]].mean(axis=0)[2])
    worse = float(np.mean(quality < quality[t]))
    return (f"| {frame} | {iterations} | {check[t].min():.3f} | {', '.join(f'{x:.3f}' for x in check[t])} | "
            f"{centroid[t]:.3f} | {depth:.2f} | {int(on_boundary[tets[t]].sum())} | "
            f"{quality[t]:.2f} ({100 * worse:.0f} %) "
            f"| {centroid.min():.3f} to {centroid.max():.3f} | {int(np.sum(check.min(axis=1) < 0.5))} |")


def main(scene: Path, frames: int = typer.Option(8, min=1),
         device: str = typer.Option("", help="replace the scene's [physics] device (cpu, cuda)")) -> None:
    setup = load_setup(scene)
    if device:
        physics = setup.scene.physics.model_copy(update={"device": device})
        setup = dataclasses.replace(setup, scene=setup.scene.model_copy(update={"physics": physics}))
    solvers, iterations = [], []
    solve_frame = QuasiStaticSolver.solve_frame

    def recording(self, poses):
        result = solve_frame(self, poses)
        solvers[:] = [self]
        iterations.append(result.record.iterations)  # a force-target press: its last trial's (trajectory.py)
        return result

    QuasiStaticSolver.solve_frame = recording
    print(f"{scene}, physics device {physics_device(setup.scene.physics.device)}, {frames} frame(s)\n")
    print("| frame | Newton iterations | smallest check-point J | that tet's 4 check points | its centroid J | "
          "its depth (mm) | its boundary vertices | its quality (tets worse) | centroid J, all tets | "
          "tets with a check point below 0.5 |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    mesh = None  # (quality, boundary vertices, top z): the rest mesh's, found once
    try:
        for f in simulate_frames(setup, frames, StageClock()):
            if not solvers:  # a frame without contact: nothing deformed
                continue
            solver = solvers[0]
            V, T = solver.vertices_mm, solver.tets
            mesh = mesh or (tet_quality(V, T), boundary_vertices(T), float(V[:, 2].max()))
            check, centroid = det_f_fields(solver)
            print(frame_row(f.frame, iterations[-1], check, centroid, mesh[0], mesh[1], V, T, mesh[2]), flush=True)
    finally:
        QuasiStaticSolver.solve_frame = solve_frame


if __name__ == "__main__":
    typer.run(main)
