"""The simulator stage as the dataset sees it: per frame, the deformed gel, the markers' positions, the
indenters' poses and forces, and the solver record.

A contact-free scene never meshes the gel or calls the FEM solver: every frame is the rest state.
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


def _depth_below_surface(setup: SceneSetup, k: int, pose: np.ndarray) -> float:
    v = setup.indenters[k].mesh.mesh.vertices @ pose[:3, :3].T + pose[:3, 3]
    return float(max(0.0, setup.sensor.gel_size_mm[2] - v[:, 2].min()))


def simulate_frames(setup: SceneSetup, frames: int, clock) -> Iterator[PhysicsFrame]:
    """``frames`` physics frames of ``setup``, in order (each warm-starts from the last)."""
    if not setup.has_contact:
        for f in range(frames):
            yield PhysicsFrame(f, setup.sensor.markers_rest_gel_mm, None, None, None, [], [], [], dict(REST_SOLVER))
        return
    from transtac_sim.physics.scene_adapter import solve_scene

    yield from solve_scene(setup, frames, clock)
