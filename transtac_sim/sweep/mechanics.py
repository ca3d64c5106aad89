"""The sweep's FEM cache: one solve per mechanical configuration, any marker layout embedded afterwards.

Markers do not change the mechanics (they are embedded in the tet mesh after the solve), so the FEM of a
benchmark sequence depends only on the gel (size, thickness, material, stiffness), the mesh and physics
settings and the indenter and its trajectory (``mechanics_key``). ``solve`` runs the simulator's own
physics stage (``transtac_sim.simulation.simulate_frames``) once and stores, per frame, the displacement
at the mesh vertices *and at every edge midpoint*: the vertex and edge-midpoint values determine a
quadratic (P2) field on each tet exactly, and a linear (P1) one too. ``replay`` embeds another layout's
markers (tet + barycentric, as the meshing stage does) and evaluates

    u(b) = sum_i b_i (2 b_i - 1) u_i + sum_{i<j} 4 b_i b_j u_ij

which is the solver's own interpolation (``displacement_at``) for both element orders. The midpoints are
obtained from the same solve by appending them to the markers of the setup that is solved (the simulator
interpolates the FEM field at every marker): no change to the simulator is needed.

Cache entries: ``<cache>/<key>.npz`` (written atomically) or ``<key>.failed.json`` with the reason.
"""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from transtac_sim.dataset.sequence import StageClock
from transtac_sim.scene_setup import SceneSetup
from transtac_sim.simulation import PhysicsFrame, SimulationFailed, simulate_frames
from transtac_sim.sweep.config import key_of
from transtac_sim.writer.atomic import atomic_write, write_json

CACHE_VERSION = 1
_PAIRS = np.array([(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)])


def mechanics_key(setup: SceneSetup, frames: int) -> str:
    """Hash of everything the FEM of ``setup`` depends on; the marker layout and the cameras are not in it."""
    sc, s = setup.scene, setup.sensor
    return key_of({
        "version": CACHE_VERSION, "frames": frames, "gel_size_mm": list(s.gel_size_mm), "gel": s.gel.model_dump(mode="json"),
        "mesh": sc.mesh.model_dump(mode="json"), "physics": sc.physics.model_dump(mode="json"),
        "indenters": [{"config": i.config.model_dump(mode="json", exclude={"color_rgb"}), "mesh_file": str(i.config.mesh),
                       "start_pose": np.round(i.start_pose, 9).tolist()} for i in setup.indenters],
    })


def tet_edges(tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges (E, 2) of a tet mesh and, per tet, the ids of its six edges (M, 6) in _PAIRS order."""
    e = np.sort(tets[:, _PAIRS], axis=2).reshape(-1, 2)
    edges, inverse = np.unique(e, axis=0, return_inverse=True)
    return edges, inverse.reshape(len(tets), 6)


class FemCache:
    def __init__(self, root: Path):
        self.root = Path(root)

    def path(self, key: str) -> Path:
        return self.root / f"{key}.npz"

    def failed_path(self, key: str) -> Path:
        return self.root / f"{key}.failed.json"

    def status(self, key: str) -> str | None:
        """'done', 'failed' or None (not solved yet)."""
        return "done" if self.path(key).is_file() else "failed" if self.failed_path(key).is_file() else None

    def failure(self, key: str) -> str:
        return json.loads(self.failed_path(key).read_text())["reason"]

    def solve(self, setup: SceneSetup, frames: int) -> dict:
        """Solve ``setup``'s FEM (unless cached) and store it; returns {key, status, seconds, reused}."""
        key = mechanics_key(setup, frames)
        if self.status(key):
            return {"key": key, "status": self.status(key), "seconds": 0.0, "reused": True}
        from transtac_sim.meshing import mesh_gel

        t0 = time.perf_counter()
        clock = StageClock()
        with clock("mesh"):
            g = mesh_gel(setup).mesh  # cached on disk by its inputs: the solve below meshes to the same
        edges, _ = tet_edges(g.tets)
        mid = g.vertices_mm[edges].mean(axis=1)
        k = len(setup.sensor.markers_rest_gel_mm)
        probe = dataclasses.replace(setup, sensor=dataclasses.replace(
            setup.sensor, markers_rest_gel_mm=np.vstack([setup.sensor.markers_rest_gel_mm, mid])))
        u_vertex, u_mid, markers, poses, forces, depths, solver = [], [], [], [], [], [], []
        try:
            for ph in simulate_frames(probe, frames, clock):
                u_vertex.append(ph.surface_vertices_gel_mm - ph.rest_vertices_gel_mm)
                u_mid.append(ph.markers_gel_mm[k:] - mid)
                markers.append(ph.markers_gel_mm[:k])
                poses.append(np.asarray(ph.indenter_poses))
                forces.append(np.asarray(ph.forces_n))
                depths.append(np.asarray(ph.depths_mm))
                solver.append(ph.solver)
        except SimulationFailed as e:
            write_json(self.failed_path(key), {"reason": str(e)})
            return {"key": key, "status": "failed", "seconds": time.perf_counter() - t0, "reused": False}
        if not np.array_equal(ph.rest_vertices_gel_mm, g.vertices_mm):
            raise RuntimeError("the FEM meshed the gel differently from the mesh cache; cannot record its field")
        seconds = time.perf_counter() - t0

        def write(f):
            np.savez_compressed(f, vertices_mm=g.vertices_mm, tets=g.tets, edges=edges, u_vertex=np.asarray(u_vertex),
                                u_mid=np.asarray(u_mid), markers_solved=np.asarray(markers), poses=np.asarray(poses),
                                forces=np.asarray(forces), depths=np.asarray(depths),
                                meta=json.dumps({"solver": solver, "seconds": seconds, "timings": clock.seconds}))

        self.root.mkdir(parents=True, exist_ok=True)
        atomic_write(self.path(key), write)
        return {"key": key, "status": "done", "seconds": seconds, "reused": False}

    def replay(self, setup: SceneSetup, frames: int) -> tuple[list[PhysicsFrame], dict]:
        """The physics frames of ``setup`` from the cached field of its mechanics, with ``setup``'s own
        markers embedded; and the cache entry's meta (solver records, seconds of the original solve)."""
        from transtac_sim.meshing import GelMesh, embed_points

        key = mechanics_key(setup, frames)
        with np.load(self.path(key)) as z:
            d = {n: z[n] for n in z.files}
        meta = json.loads(str(d["meta"]))
        V, T = d["vertices_mm"], d["tets"]
        emb = embed_points(V, T, setup.sensor.markers_rest_gel_mm)
        _, tet_edge_ids = tet_edges(T)
        b = emb.barycentric
        wv = b * (2 * b - 1)  # (K, 4) vertex weights
        we = 4 * b[:, _PAIRS[:, 0]] * b[:, _PAIRS[:, 1]]  # (K, 6) edge-midpoint weights
        vid, eid = T[emb.tet_index], tet_edge_ids[emb.tet_index]
        faces = GelMesh(V, T).boundary_faces()
        out = []
        for f in range(len(d["u_vertex"])):
            uv, um = d["u_vertex"][f], d["u_mid"][f]
            u = np.einsum("kc,kcd->kd", wv, uv[vid]) + np.einsum("kc,kcd->kd", we, um[eid])
            out.append(PhysicsFrame(f, setup.sensor.markers_rest_gel_mm + u, V + uv, V, faces,
                                    list(d["poses"][f]), list(d["forces"][f]), [float(x) for x in d["depths"][f]],
                                    meta["solver"][f]))
        return out, meta
