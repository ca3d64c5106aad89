"""The simulator stage as the dataset sees it: per frame, the deformed gel, the markers' positions, the
indenters' poses and forces, and the solver record.

A contact-free scene (no indenter, or indenters that only hold above the gel) never meshes the gel or calls
the FEM solver: every frame is the rest state, with the indenters at their start poses. A frame
in which an indenter is pressed into the gel's plane but exerts no force fails (``check_pressed_indenters_touch``).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from transtac_sim.scene_setup import SceneSetup


class SimulationFailed(RuntimeError):
    """The physics of ``frame`` could not be solved; the message says why and what was tried."""

    def __init__(self, frame: int, message: str):
        self.frame = frame
        super().__init__(f"frame {frame}: {message}")


@dataclass(frozen=True)
class PhysicsFrame:
    frame: int
    markers_gel_mm: np.ndarray  # (K, 3) marker centres, gel frame
    surface_vertices_gel_mm: np.ndarray | None  # deformed gel mesh vertices (gel frame); None = rest box
    rest_vertices_gel_mm: np.ndarray | None  # the same vertices at rest
    surface_faces: np.ndarray | None  # (F, 3) boundary triangles of the gel mesh, outward
    indenter_poses: list[np.ndarray]  # 4x4 per indenter, indenter frame -> gel frame
    forces_n: list[np.ndarray]  # (3,) force of each indenter on the gel, N
    depths_mm: list[float]  # how far each indenter's lowest point is below the undeformed surface
    solver: dict  # converged, iterations, residual, seconds (DESIGN.md labels.json)


REST_SOLVER = {"converged": True, "iterations": 0, "residual": 0.0, "seconds": 0.0}
#: An indenter whose lowest point is more than this below the undeformed contact surface is pressed in (mm).
PRESSED_MM = 0.05


def _depth_below_surface(setup: SceneSetup, k: int, pose: np.ndarray) -> float:
    v = setup.indenters[k].mesh.mesh.vertices @ pose[:3, :3].T + pose[:3, 3]
    return float(max(0.0, setup.sensor.gel_size_mm[2] - v[:, 2].min()))


def check_pressed_indenters_touch(setup: SceneSetup, frame: int, poses: list[np.ndarray],
                                  forces_n: list[np.ndarray], depths_mm: list[float]) -> None:
    """Refuse a frame in which an indenter is pressed in (lowest point more than PRESSED_MM below the
    undeformed surface) but the FEM gives it no force at all: its labels would report a press that touched
    nothing. Raises SimulationFailed naming the frame and the indenter, and saying whether the indenter's
    pressed-in part lies beside the gel's top face (a placement error: start_xy_mm, the mesh's origin,
    ``anchor``) or over it (a contact smaller than the mesh resolves). Gel frame, mm, N."""
    w, h, t = setup.sensor.gel_size_mm
    for ind, pose, force, depth in zip(setup.indenters, poses, forces_n, depths_mm, strict=True):
        if depth <= PRESSED_MM or np.any(np.asarray(force) != 0.0):
            continue
        mesh = ind.mesh.mesh
        v = mesh.vertices @ pose[:3, :3].T + pose[:3, 3]
        # every triangle reaching below the surface: its xy box holds the whole pressed-in part
        low = v[mesh.faces[(v[mesh.faces][:, :, 2] < t).any(axis=1)].ravel(), :2]
        lo, hi = low.min(axis=0), low.max(axis=0)
        where = (f"its part below the surface lies within x {lo[0]:.2f}..{hi[0]:.2f} mm, "
                 f"y {lo[1]:.2f}..{hi[1]:.2f} mm (gel frame)")
        if lo[0] >= w / 2 or hi[0] <= -w / 2 or lo[1] >= h / 2 or hi[1] <= -h / 2:
            why = (f"{where}, beside the gel's top face (x -{w / 2:g}..{w / 2:g}, y -{h / 2:g}..{h / 2:g} mm): "
                   f"check its start_xy_mm and where its mesh's origin lies (anchor = {ind.config.anchor!r}; "
                   "'footprint' places it by its shape)")
        else:
            why = (f"{where}, over the gel, but no contact point of the gel's surface is inside it: the contact "
                   "is smaller than the mesh resolves (lower [mesh] contact_edge_mm)")
        raise SimulationFailed(frame, f"indenter {ind.config.name!r} is pressed {depth:.3g} mm below the "
                                      f"undeformed contact surface but exerts no force; {why}")


def simulate_frames(setup: SceneSetup, frames: int, clock) -> Iterator[PhysicsFrame]:
    """``frames`` physics frames of ``setup``, in order (each warm-starts from the last)."""
    if not setup.has_contact:
        poses = [i.start_pose for i in setup.indenters]
        for f in range(frames):
            yield PhysicsFrame(f, setup.sensor.markers_rest_gel_mm, None, None, None, poses,
                               [np.zeros(3) for _ in poses], [0.0 for _ in poses], dict(REST_SOLVER))
        return
    yield from _solve_with_fem(setup, frames, clock)


def physics_device(name: str) -> str:
    """The Warp device a scene's ``[physics] device`` names: "auto" is cuda where a GPU is available, else cpu."""
    if name != "auto":
        return name
    import warp as wp

    return "cuda" if wp.is_cuda_available() else "cpu"


def _solve_with_fem(setup: SceneSetup, frames: int, clock) -> Iterator[PhysicsFrame]:
    from transtac_sim.meshing import mesh_gel
    from transtac_sim.physics import (
        ElasticMaterial,
        IndenterStartsInsideGel,
        QuasiStaticSolver,
        RigidIndenter,
        SolverDidNotConverge,
        SolverSettings,
    )
    from transtac_sim.physics.trajectory import simulate_sequence

    with clock("mesh"):
        meshed = mesh_gel(setup)
    g, cfg = meshed.mesh, setup.scene.physics
    gel = setup.sensor.gel
    with clock("physics_setup"):
        solver = QuasiStaticSolver(
            g.vertices_mm, g.tets, ElasticMaterial(gel.youngs_modulus_mpa, gel.poisson_ratio),
            [RigidIndenter.from_trimesh(i.config.name, i.mesh.mesh, i.config.friction) for i in setup.indenters],
            settings=SolverSettings(degree=cfg.degree, newton_tol_mm=cfg.newton_tol_mm, linear_solver=cfg.linear_solver,
                                    slip_eps_mm=cfg.friction_slip_mm, friction_lag_moves=cfg.friction_lag_moves,
                                    coarse_cell_mm=cfg.coarse_cell_mm or None,
                                    newton_force_rtol=cfg.newton_force_rtol or None,
                                    newton_no_progress_steps=cfg.newton_no_progress_steps),
            device=physics_device(cfg.device))
    faces = g.boundary_faces()
    thickness = setup.sensor.gel_size_mm[2]
    sequence = simulate_sequence(solver, [i.start_pose for i in setup.indenters],
                                 [list(i.config.trajectory) for i in setup.indenters], thickness)
    for f in range(frames):
        try:
            with clock("physics"):
                res = next(sequence, None)
                if res is None:
                    raise SimulationFailed(f, f"the scene's trajectories have only {f} frame(s)")
                markers = setup.sensor.markers_rest_gel_mm + solver.displacement_at(
                    meshed.markers.tet_index, meshed.markers.barycentric)
        except (SolverDidNotConverge, IndenterStartsInsideGel) as e:
            raise SimulationFailed(f, str(e)) from None
        r = res.record
        poses = [np.asarray(p) for p in res.poses]
        forces = [np.asarray(x) for x in res.forces_n]
        depths = [_depth_below_surface(setup, k, p) for k, p in enumerate(poses)]
        check_pressed_indenters_touch(setup, f, poses, forces, depths)
        yield PhysicsFrame(
            f, markers, g.vertices_mm + res.displacement_mm, g.vertices_mm, faces, poses, forces, depths,
            {"converged": bool(r.converged), "iterations": int(r.iterations), "residual": float(r.residual),
             "seconds": float(r.seconds), "min_det_f": float(r.min_det_f), "substeps": int(r.substeps),
             "friction_lag_residual_n": float(r.friction_lag_residual_n),
             "failed_steps": [{"from": float(s.start), "to": float(s.end), "iterations": int(s.iterations),
                               "why": str(s.why)} for s in r.failed_steps]},
        )
