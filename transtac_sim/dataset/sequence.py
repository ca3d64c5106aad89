"""One sequence of a dataset: physics frame by frame (warm-started), then for every frame not yet on disk:
render, camera model, labels, write. Runs in a worker process or a Ray task; returns one status record
per frame with its per-stage seconds.

A frame counts as done when it is complete (``frame_writer.frame_problems``); one whose files were damaged after
an earlier run wrote it is solved and written again, its record saying why (``redone``).

A frame whose physics fails stops its sequence; the failure is kept in ``<dataset>/.resume/<sequence>.json``
(resume state, not part of the dataset contract), so that a resumed run does not solve the same sequence up
to the same failure again (minutes for a sharp slide that exhausts the sub-stepping); ``retry_failed`` (the
CLI's ``--retry-failed``, e.g. after a solver change) solves it again.

Stages run only when an output needs them: no FEM for a contact-free scene (the gel stays at rest), no
render without illuminations or AOVs, no labels when ``outputs.labels`` is false.
"""

from __future__ import annotations

import dataclasses
import json
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from transtac_sim.config.scene import Scene
from transtac_sim.dataset import contract
from transtac_sim.dataset.frame_writer import LABELS_MISSING, FrameOutput, frame_problems, write_frame
from transtac_sim.dataset.randomize import sequence_variant
from transtac_sim.writer.atomic import write_json


class StageClock:
    """Seconds spent per stage, summed."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def __call__(self, stage: str):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[stage] = self.seconds.get(stage, 0.0) + time.perf_counter() - t0


def run_sequence(task) -> list[dict]:
    from transtac_sim import simulation

    resolved = json.loads(task.scene_json)
    limit = resolved.pop("frames_per_sequence")
    scene = Scene.model_validate(resolved)
    root = Path(task.root)
    seq = contract.sequence_name(task.index)
    problems = {f: frame_problems(root, seq, f, scene.outputs) for f in range(limit)}
    todo = [f for f in range(limit) if problems[f]]
    damaged = {f: ", ".join(p) for f, p in problems.items() if p and p != [LABELS_MISSING]}  # finished, since damaged
    if not todo:
        return [{"sequence": seq, "frame": f, "status": "done", "skipped": True} for f in range(limit)]
    failure = failure_record(root, seq)
    if failure.is_file() and not task.retry_failed:
        known = json.loads(failure.read_text())
        if known["frames"] == limit and todo == list(range(known["frame"], limit)):
            return [{"sequence": seq, "frame": f, "status": "done", "skipped": True} for f in range(known["frame"])] \
                + known["records"]
    clock = StageClock()
    with clock("setup"):
        setup, variant = sequence_setup(scene, Path(task.scene_path), task.index)
    out = scene.outputs
    renderer = None
    records: list[dict] = []
    stages = {"setup"}
    try:
        for phys in simulation.simulate_frames(setup, limit, clock):
            f = phys.frame
            if f not in todo:
                records.append({"sequence": seq, "frame": f, "status": "done", "skipped": True})
                continue
            images, depth, views = {}, {}, {}
            if out.illuminations or out.aovs or out.labels:
                from transtac_sim.dataset.render_stage import FrameRenderer

                if renderer is None:
                    with clock("render_setup"):
                        renderer = FrameRenderer(setup, variant, clock, phys.rest_vertices_gel_mm, phys.surface_faces)
                images, depth, views = renderer.render(phys, seed=frame_seed(scene.seed, task.index, f))
            labels = frame_labels(seq, f, f / out.frame_rate_hz, setup, phys, views)
            with clock("write"):
                write_frame(root, FrameOutput(seq, f, labels, images, depth))
            redone = {"redone": damaged[f]} if f in damaged else {}
            records.append({"sequence": seq, "frame": f, "status": "done"} | redone)
    except simulation.SimulationFailed as e:
        done = {r["frame"] for r in records}
        failed = [{"sequence": seq, "frame": f, "status": "failed", "reason": str(e) if f == e.frame else
                   f"not simulated: frame {e.frame} of this sequence failed"} for f in range(limit) if f not in done]
        write_json(failure, {"frames": limit, "frame": e.frame, "records": failed})
        records += failed
    else:
        failure.unlink(missing_ok=True)
    stages |= set(clock.seconds)
    if records:
        records[0]["timings"] = clock.seconds
        records[0]["stages"] = sorted(stages)
    return records


def sequence_setup(scene: Scene, scene_path: Path, index: int):
    """(setup, variant) of sequence ``index`` of ``scene``: its randomised indenters, trajectory, friction, layout
    and gel stiffness, as ``generate`` solves and renders it."""
    from transtac_sim.scene_setup import build_setup

    variant = sequence_variant(scene, index)
    setup = build_setup(variant.scene, scene_path, marker_seed=variant.marker_seed)
    if variant.youngs_modulus_mpa is not None:
        gel = setup.sensor.gel.model_copy(update={"youngs_modulus_mpa": variant.youngs_modulus_mpa})
        setup = dataclasses.replace(setup, sensor=dataclasses.replace(setup.sensor, gel=gel))
    return setup, variant


def failure_record(root: Path, sequence: str) -> Path:
    """Where a sequence's failed frame is kept for resuming (see the module docstring)."""
    return Path(root) / ".resume" / f"{sequence}.json"


def frame_seed(scene_seed: int, sequence: int, frame: int) -> int:
    """The render and sensor-noise seed of one frame: independent of run order and worker count."""
    return int(np.random.default_rng([scene_seed, sequence, frame]).integers(2**26))


def frame_labels(seq: str, frame: int, time_s: float, setup, phys, views: dict) -> dict:
    """``labels.json`` of DESIGN.md section 4: 3D in the left camera's frame (mm), 2D per camera."""
    sensor = setup.sensor
    rest = sensor.gel_to_left(sensor.markers_rest_gel_mm)
    now = sensor.gel_to_left(phys.markers_gel_mm)
    to_left = np.eye(4)
    to_left[:3, 3] = sensor.gel_origin_in_left_mm
    markers = []
    for i in range(len(rest)):
        m = {"id": i, "xyz_rest_mm": rest[i].tolist(), "xyz_mm": now[i].tolist()}
        for cam, v in views.items():
            m[cam] = dict(v[i])
            if m[cam]["uv_centroid"] is not None:  # measured on a float32 render whose last bits depend on
                m[cam]["uv_centroid"] = [round(c, 3) for c in m[cam]["uv_centroid"]]  # the threads' order
        markers.append(m)
    return {
        "sequence": seq, "frame": frame, "time_s": time_s,
        "indenters": [{"name": ind.config.name, "pose_mm": (to_left @ pose).tolist(),
                       "force_n": force.tolist(), "depth_mm": depth}
                      for ind, pose, force, depth in zip(setup.indenters, phys.indenter_poses, phys.forces_n,
                                                         phys.depths_mm, strict=True)],
        "solver": phys.solver,
        "markers": markers,
    }
