"""``transtac-sim simulate``: the physics stage alone, written to a folder, frame by frame.

Everything is in the gel frame (origin at the centre of the bonded face, x right, y down, z away from the
cameras; contact surface z = thickness), millimetres and newtons; every file is written atomically.
```
DIR/mesh.npz            vertices_mm (V,3) rest tet-mesh vertices, tets (T,4), boundary_faces (F,3) outward,
                        marker_tets (K,), marker_barycentric (K,4) (the markers' embedding in the tets);
                        always: gel_size_mm (3,), marker_ids (K,), markers_rest_mm (K,3).
                        A contact-free scene is never meshed: only the "always" arrays.
DIR/frames/NNNNNN.npz   vertices_mm (V,3) deformed vertices (contact scenes only), markers_mm (K,3) marker
                        centres (row i is marker_ids[i]), indenter_poses_mm (n,4,4) indenter -> gel frame
                        (translation in mm), forces_n (n,3) force of each indenter on the gel, depths_mm (n,)
DIR/frames/NNNNNN.json  frame, time_s, solver {converged, iterations, residual, seconds, min_det_f, substeps,
                         friction_lag_residual_n, failed_steps [{from, to, iterations, why}]},
                        indenters [{name, pose_mm, force_n, depth_mm}], max_marker_displacement_mm
DIR/summary.json        kind, scene, scene_config, status (running | done | failed), frames_requested,
                        frames_written, failure {frame, message} or null, per-stage and per-frame seconds
DIR/displacement.png    the last written frame's displacement field (reports/displacement_figure.py)
```
A run that fails at frame k keeps frames 0..k-1, records the failure in summary.json and still draws
frame k-1. A folder is written into only when it is empty, new, or holds an earlier ``simulate`` output
of the same scene (whose frame files are then replaced), unless ``overwrite`` is given. A run into a folder
that holds files already is staged inside it and moved in when it ends, done or failed at a frame (staging.py):
an interrupted or crashed run leaves the earlier one as it was.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from transtac_sim import __version__
from transtac_sim.scene_setup import SceneSetup
from transtac_sim.simulation import PhysicsFrame, SimulationFailed
from transtac_sim.writer.atomic import write_json, write_npz
from transtac_sim.writer.staging import own_entries, staged_output

KIND = "transtac-sim simulate"
FORMAT_VERSION = 1
_FRAME_FILE = re.compile(r"^\d{6}\.(npz|json)$")


class OutputFolderInUse(RuntimeError):
    """The output folder holds something other than an earlier simulate run of the same scene."""


@dataclass
class SimulateReport:
    out: Path
    frames_requested: int
    frames_written: int = 0
    failure: dict | None = None  # {"frame": k, "message": why}
    timings: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0
    figure: Path | None = None
    max_force_n: float = 0.0  # largest |F| of any indenter over the written frames
    max_marker_displacement_mm: float = 0.0


def frame_path(out: Path, frame: int, ext: str) -> Path:
    return Path(out) / "frames" / f"{frame:06d}.{ext}"


def frame_count(setup: SceneSetup, frames: int | None) -> int:
    """Frames to simulate: ``frames`` (default the trajectory's length), at most the trajectory's length
    for a scene with contact (a contact-free scene repeats its rest state as often as asked)."""
    n = setup.scene.frame_count
    if not frames:
        return n
    return min(frames, n) if setup.has_contact else frames


def check_output_folder(out: Path, scene_config: dict, overwrite: bool) -> None:
    """Raise OutputFolderInUse unless ``out`` may be written (see the module docstring)."""
    out = Path(out)
    if not out.exists():
        return
    if not out.is_dir():
        raise OutputFolderInUse(f"{out} exists and is not a folder; choose another --out")
    if overwrite or not own_entries(out):
        return
    try:
        old = json.loads((out / "summary.json").read_text())
    except (OSError, ValueError):
        old = None
    if isinstance(old, dict) and old.get("kind") == KIND:
        if old.get("scene_config") == scene_config:
            return
        what = f"holds the simulate output of another scene ({old.get('scene')!r}) or of a changed scene file"
    else:
        what = "is not empty and holds no simulate output"
    raise OutputFolderInUse(f"{out} {what}; choose another --out, or pass --overwrite to replace its files "
                            "(nothing was changed)")


def _earlier_files(out: Path) -> list[Path]:
    """An earlier run's frame files and picture in ``out`` (only files this command writes)."""
    frames = [p for p in (out / "frames").glob("*") if _FRAME_FILE.match(p.name) and p.is_file()]
    return frames + [p for p in (out / "displacement.png",) if p.is_file()]


def _mesh_arrays(setup: SceneSetup, meshed) -> dict[str, np.ndarray]:
    m = setup.sensor.markers_rest_gel_mm
    arrays = {"gel_size_mm": np.asarray(setup.sensor.gel_size_mm, dtype=np.float64),
              "marker_ids": np.arange(len(m)), "markers_rest_mm": np.asarray(m, dtype=np.float64)}
    if meshed is not None:
        g = meshed.mesh
        arrays |= {"vertices_mm": g.vertices_mm, "tets": g.tets, "boundary_faces": g.boundary_faces(),
                   "marker_tets": meshed.markers.tet_index, "marker_barycentric": meshed.markers.barycentric}
    return arrays


def write_frame(out: Path, setup: SceneSetup, phys: PhysicsFrame) -> dict:
    """Write one frame's npz and json; returns the json record."""
    n = len(setup.indenters)
    poses = np.asarray(phys.indenter_poses, dtype=np.float64).reshape(n, 4, 4)
    forces = np.asarray(phys.forces_n, dtype=np.float64).reshape(n, 3)
    depths = np.asarray(phys.depths_mm, dtype=np.float64).reshape(n)
    arrays = {"markers_mm": np.asarray(phys.markers_gel_mm, dtype=np.float64), "indenter_poses_mm": poses,
              "forces_n": forces, "depths_mm": depths}
    if phys.surface_vertices_gel_mm is not None:
        arrays["vertices_mm"] = np.asarray(phys.surface_vertices_gel_mm, dtype=np.float64)
    # the rest state is exact: det F = 1 and nothing to sub-step
    solver = dict(phys.solver)
    solver.setdefault("min_det_f", 1.0)
    solver.setdefault("substeps", 0)
    solver.setdefault("friction_lag_residual_n", 0.0)
    solver.setdefault("failed_steps", [])
    du = np.linalg.norm(phys.markers_gel_mm - setup.sensor.markers_rest_gel_mm, axis=1)
    record = {
        "frame": phys.frame, "time_s": phys.frame / setup.scene.outputs.frame_rate_hz, "solver": solver,
        "indenters": [{"name": ind.config.name, "pose_mm": poses[k].tolist(), "force_n": forces[k].tolist(),
                       "depth_mm": float(depths[k])} for k, ind in enumerate(setup.indenters)],
        "max_marker_displacement_mm": float(du.max()) if len(du) else 0.0,
    }
    write_npz(frame_path(out, phys.frame, "npz"), **arrays)
    write_json(frame_path(out, phys.frame, "json"), record)
    return record


def draw_frame(path: Path, setup: SceneSetup, phys: PhysicsFrame, meshed) -> Path:
    from transtac_sim.reports.displacement_figure import IndenterView, save_displacement_figure

    views = [IndenterView(ind.config.name, np.asarray(ind.mesh.mesh.vertices), np.asarray(ind.mesh.mesh.faces),
                          np.asarray(phys.indenter_poses[k]), np.asarray(phys.forces_n[k]))
             for k, ind in enumerate(setup.indenters)]
    contact = phys.surface_vertices_gel_mm is not None
    return save_displacement_figure(
        path, title=setup.scene.name, frame=phys.frame, gel_size_mm=setup.sensor.gel_size_mm,
        markers_rest_mm=setup.sensor.markers_rest_gel_mm, markers_mm=phys.markers_gel_mm,
        rest_vertices_mm=phys.rest_vertices_gel_mm if contact else None,
        vertices_mm=phys.surface_vertices_gel_mm if contact else None,
        tets=meshed.mesh.tets if contact else None, boundary_faces=phys.surface_faces if contact else None,
        indenters=views)


def _simulate_into(work: Path, setup: SceneSetup, total: int, report: SimulateReport, clock, per_frame: list[float],
                   summary: Callable[[str], None], on_frame: Callable[[int, int, float], None] | None):
    """Mesh (a contact scene), write mesh.npz, then solve and write ``total`` frames into ``work``, updating
    ``report``, ``per_frame`` (s) and the running summary; a SimulationFailed ends the frames with
    ``report.failure`` set. Returns the last frame written (or None) and the meshed gel (or None)."""
    from transtac_sim import simulation

    meshed = None
    if setup.has_contact:
        from transtac_sim.meshing import mesh_gel

        with clock("mesh"):
            meshed = mesh_gel(setup)
    write_npz(work / "mesh.npz", **_mesh_arrays(setup, meshed))
    last: PhysicsFrame | None = None
    t_frame = time.perf_counter()
    try:
        for phys in simulation.simulate_frames(setup, total, clock):
            with clock("write"):
                record = write_frame(work, setup, phys)
            per_frame.append(time.perf_counter() - t_frame)
            t_frame = time.perf_counter()
            last = phys
            report.frames_written = phys.frame + 1
            forces = [np.linalg.norm(f) for f in phys.forces_n]
            report.max_force_n = max([report.max_force_n, *map(float, forces)])
            report.max_marker_displacement_mm = max(report.max_marker_displacement_mm,
                                                    record["max_marker_displacement_mm"])
            summary("running")
            if on_frame:
                on_frame(report.frames_written, total, per_frame[-1])
    except SimulationFailed as e:
        prefix = f"frame {e.frame}: "
        message = str(e)[len(prefix):] if str(e).startswith(prefix) else str(e)
        report.failure = {"frame": e.frame, "message": message}
    return last, meshed


def simulate_to_folder(setup: SceneSetup, out: Path, *, frames: int | None = None, overwrite: bool = False,
                       on_frame: Callable[[int, int, float], None] | None = None) -> SimulateReport:
    """Simulate ``frames`` frames of ``setup`` into ``out`` (module docstring). ``on_frame(done, total,
    seconds of that frame)`` reports progress. A SimulationFailed ends the run with ``report.failure`` set;
    any other exception is recorded in summary.json (where no earlier run is replaced) and raised."""
    from transtac_sim.dataset.sequence import StageClock

    t0 = time.perf_counter()
    out = Path(out)
    scene_config = json.loads(setup.scene.model_dump_json())
    check_output_folder(out, scene_config, overwrite)
    total = frame_count(setup, frames)
    report = SimulateReport(out, total)
    clock = StageClock()
    per_frame: list[float] = []
    with staged_output(out, _earlier_files, last=("summary.json",)) as work:

        def summary(status: str) -> None:
            write_json(work / "summary.json", {
                "kind": KIND, "format_version": FORMAT_VERSION,
                "generator": {"name": "transtac_sim", "version": __version__},
                "scene": setup.scene.name, "scene_file": str(setup.path), "scene_config": scene_config,
                "status": status, "frames_requested": total, "frames_written": report.frames_written,
                "failure": report.failure, "contact": setup.has_contact,
                "indenters": [i.config.name for i in setup.indenters],
                "markers": len(setup.sensor.markers_rest_gel_mm),
                "max_force_n": report.max_force_n, "max_marker_displacement_mm": report.max_marker_displacement_mm,
                "timings_s": clock.seconds, "seconds_per_frame": per_frame, "seconds": time.perf_counter() - t0,
                "displacement_png": report.figure.name if report.figure else None,
            })

        summary("running")
        try:
            last, meshed = _simulate_into(work, setup, total, report, clock, per_frame, summary, on_frame)
            if last is not None:
                with clock("figure"):
                    report.figure = draw_frame(work / "displacement.png", setup, last, meshed)
        except BaseException as e:
            report.failure = {"frame": report.frames_written, "message": f"{type(e).__name__}: {e}"}
            if work == out:  # staged elsewhere, the earlier run stays as it was
                summary("failed")
            raise
        report.timings = dict(clock.seconds)
        report.seconds = time.perf_counter() - t0
        summary("failed" if report.failure else "done")
    report.figure = out / report.figure.name if report.figure else None
    return report
