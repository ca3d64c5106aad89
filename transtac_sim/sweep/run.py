"""``transtac-sim sweep SWEEP.toml --out DIR``: every point of a sweep file (``sweep.config``) simulated,
rendered, run through the perception pipeline and scored (``sweep.scoring``); a table, plots and a report.

Work is split so that each point does only what it needs:

1. mechanics: one FEM solve per distinct mechanical configuration and benchmark motion (gel, stiffness,
   mesh, physics, indenter and trajectory; not the markers, not the cameras; a point's scenes:
   ``sweep.point_scenes``), cached in ``DIR/cache/fem/`` (``sweep.mechanics``); points that differ only in
   marker layout or cameras reuse it.
2. render + score: one task per distinct rendered set (everything but the pipeline settings), written as
   a dataset under ``DIR/renders/<key>/`` (UV images of both cameras and labels.json; a frame is complete
   once its labels.json exists); the points that differ only in pipeline settings (detector, matcher) score
   the same images. Each point's result goes to ``DIR/points/<key>/result.json``.

Resume: re-running the same command skips every point with a result (a failed point is tried again),
every cached FEM solve and every complete rendered frame. The executors are those of ``generate``:
``local`` (``workers`` processes) or ``ray`` (``address`` of a cluster; ``DIR`` must then be on storage
that every machine sees). A failing point is recorded with its reason and the sweep goes on.

Outputs: ``DIR/results.csv`` (one row per point), ``DIR/plots/*.png``, ``DIR/report.md`` and
``DIR/report.html`` (the plots, the Pareto front, what was reused), ``DIR/summary.json``.
"""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from transtac_sim.config import ConfigError
from transtac_sim.executors import local_tasks, ray_tasks
from transtac_sim.sweep.config import (
    LAYOUT_KEYS,
    Point,
    Sweep,
    key_of,
    load_sweep,
)
from transtac_sim.sweep.point_scenes import point_setups, render_key
from transtac_sim.writer.atomic import write_json

Progress = Callable[[str, int, int], None]


@dataclass
class SweepReport:
    root: Path
    points: int
    done: int
    failed: list[dict]
    resumed: int  # points whose result was already there
    fem_solves: int  # FEM solves run now
    fem_cached: int  # FEM solves found in the cache (from an earlier run)
    fem_shared: int  # (point, motion) pairs served by a solve of another point
    renders: int  # rendered sets made now (or completed)
    render_shared: int  # points that scored images rendered for another point
    table: Path
    report_html: Path
    report_md: Path
    plots: list[Path] = field(default_factory=list)
    seconds: float = 0.0


# -- tasks (run in worker processes or Ray tasks) ----------------------------------------------------------

@dataclass(frozen=True)
class FemTask:
    sweep_path: str
    root: str
    values: dict
    motion: int


@dataclass(frozen=True)
class RenderTask:
    sweep_path: str
    root: str
    render_key: str
    points: tuple  # (point key, values) of every point sharing these images


def run_fem_task(task: FemTask) -> dict:
    from transtac_sim.sweep.mechanics import FemCache

    sweep = load_sweep(task.sweep_path)
    root = Path(task.root)
    setup = point_setups(sweep, task.values, root)[task.motion]
    frames = sweep.file.benchmark.frames
    return FemCache(root / "cache" / "fem").solve(setup, frames)


def _render_set(sweep: Sweep, values: dict, root: Path, folder: Path) -> dict:
    """Render (the missing frames of) the point's benchmark set into ``folder``; returns seconds spent per
    stage now and whether every frame was already there."""
    from transtac_sim.dataset import contract
    from transtac_sim.dataset.frame_writer import FrameOutput, is_complete, write_frame
    from transtac_sim.dataset.randomize import Variant
    from transtac_sim.dataset.render_stage import FrameRenderer
    from transtac_sim.dataset.sequence import StageClock, frame_labels, frame_seed
    from transtac_sim.sweep.mechanics import FemCache, mechanics_key

    cache = FemCache(root / "cache" / "fem")
    frames = sweep.file.benchmark.frames
    setups = point_setups(sweep, values, root)
    write_json(folder / "calibration.json", setups[0].sensor.calibration_json())
    clock = StageClock()
    rendered = 0
    for i, setup in enumerate(setups):
        seq = contract.sequence_name(i)
        todo = [f for f in range(frames) if not is_complete(folder, seq, f, setup.scene.outputs)]
        if not todo:
            continue
        key = mechanics_key(setup, frames)
        if cache.status(key) == "failed":
            raise RuntimeError(f"benchmark motion {i} ({setup.scene.name}): {cache.failure(key)}")
        if cache.status(key) is None:
            cache.solve(setup, frames)  # a task run alone (tests, a lost cache): solve here
            if cache.status(key) == "failed":
                raise RuntimeError(f"benchmark motion {i} ({setup.scene.name}): {cache.failure(key)}")
        with clock("embed"):
            physics, _ = cache.replay(setup, frames)
        renderer = None
        for ph in physics:
            if ph.frame not in todo:
                continue
            if renderer is None:
                with clock("render_setup"):
                    renderer = FrameRenderer(setup, Variant(setup.scene), clock, ph.rest_vertices_gel_mm, ph.surface_faces)
            images, depth, views = renderer.render(ph, seed=frame_seed(sweep.file.seed, i, ph.frame))
            labels = frame_labels(seq, ph.frame, ph.frame / setup.scene.outputs.frame_rate_hz, setup, ph, views)
            with clock("write"):
                write_frame(folder, FrameOutput(seq, ph.frame, labels, images, depth))
            rendered += 1
    old = json.loads((folder / "timings.json").read_text()) if (folder / "timings.json").is_file() else {}
    total = {k: old.get(k, 0.0) + clock.seconds.get(k, 0.0) for k in set(old) | set(clock.seconds)}
    write_json(folder / "timings.json", total)
    return {"rendered_frames": rendered, "timings": total}


def run_render_task(task: RenderTask) -> list[dict]:
    """Render one set and score every point that uses it; returns their results (also written to disk)."""
    from transtac_sim.sweep.scoring import score_dataset

    sweep = load_sweep(task.sweep_path)
    root = Path(task.root)
    folder = root / "renders" / task.render_key
    results = []
    try:
        t0 = time.perf_counter()
        rendered = _render_set(sweep, task.points[0][1], root, folder)
        render_seconds = time.perf_counter() - t0
        setups = point_setups(sweep, task.points[0][1], root)
        stack, markers = setups[0].sensor.flat_stack_json(), len(setups[0].sensor.markers_rest_gel_mm)
        fem = _fem_seconds(root, setups, sweep.file.benchmark.frames)
    except Exception as e:  # noqa: BLE001 -- a failing point is recorded and the sweep goes on
        reason = _reason(e)
        for pkey, values in task.points:
            results.append(_write_result(root, pkey, values, {"status": "failed", "reason": reason}))
        return results
    for k, (pkey, values) in enumerate(task.points):
        try:
            t0 = time.perf_counter()
            metrics = score_dataset(folder, stack, detector=values["detector"], matcher=values["matcher"])
            res = {"status": "done", "reason": "", "markers": markers, **metrics,
                   "fem_seconds": fem, "render_seconds": rendered["timings"].get("render", 0.0) + rendered["timings"].get("camera", 0.0),
                   "pipeline_seconds": time.perf_counter() - t0, "render_reused": k > 0 or rendered["rendered_frames"] == 0,
                   "render_key": task.render_key, "rendered_now_seconds": render_seconds if k == 0 else 0.0,
                   "rendered_now_frames": rendered["rendered_frames"] if k == 0 else 0}
        except Exception as e:  # noqa: BLE001
            res = {"status": "failed", "reason": _reason(e)}
        results.append(_write_result(root, pkey, values, res))
    return results


def _fem_seconds(root: Path, setups: list, frames: int) -> float:
    """Seconds the FEM solves of a point's benchmark took when they were solved (once for all points)."""
    import numpy as np

    from transtac_sim.sweep.mechanics import FemCache, mechanics_key

    cache, total = FemCache(root / "cache" / "fem"), 0.0
    for s in setups:
        with np.load(cache.path(mechanics_key(s, frames))) as z:
            total += json.loads(str(z["meta"]))["seconds"]
    return total


def _reason(e: Exception) -> str:
    msg = str(e).strip().replace("\n", " ") or type(e).__name__
    from transtac_sim.perception.errors import PerceptionInputError

    if not isinstance(e, (ConfigError, RuntimeError, ValueError, PerceptionInputError)):
        msg = f"{type(e).__name__}: {msg} ({traceback.extract_tb(e.__traceback__)[-1].name})"
    return msg


def _write_result(root: Path, pkey: str, values: dict, res: dict) -> dict:
    out = {"key": pkey, "values": values, **res}
    write_json(root / "points" / pkey / "result.json", out)
    return out


def read_result(root: Path, pkey: str) -> dict | None:
    p = root / "points" / pkey / "result.json"
    return json.loads(p.read_text()) if p.is_file() else None


# -- executors ---------------------------------------------------------------------------------------------

def _map(fn, tasks: list, executor: str, workers: int, address: str | None) -> Iterator:
    if executor == "ray":
        yield from ray_tasks(fn, tasks, address, workers)
        return
    yield from local_tasks(fn, tasks, workers)


# -- the sweep ---------------------------------------------------------------------------------------------

def run_sweep(sweep_path: str | Path, out: str | Path, *, workers: int = 1, executor: str = "local",
              address: str | None = None, progress: Progress | None = None) -> SweepReport:
    """Run (or resume) the sweep of ``sweep_path`` in ``out``; ``progress(stage, done, total)`` is called as
    FEM solves and points finish. Bad input raises ConfigError before anything is computed."""
    if executor not in ("local", "ray"):
        raise ValueError(f"executor {executor!r}: allowed local, ray")
    t_start = time.perf_counter()
    sweep = load_sweep(sweep_path)
    root = Path(out).resolve()
    old = root / "sweep.json"
    ident = {"sweep_file": str(sweep.path), "points": [p.values for p in sweep.points]}
    root.mkdir(parents=True, exist_ok=True)
    if old.is_file() and json.loads(old.read_text()).get("sweep_file") != ident["sweep_file"]:
        raise ConfigError(root / "sweep.json", [("sweep_file", "this folder holds another sweep; choose another --out")])
    write_json(old, ident)
    pkeys = {p.id: key_of(p.values) for p in sweep.points}
    todo = [p for p in sweep.points if (read_result(root, pkeys[p.id]) or {}).get("status") != "done"]
    resumed = len(sweep.points) - len(todo)

    # 1. mechanics: one solve per distinct configuration and motion
    from transtac_sim.sweep.mechanics import FemCache, mechanics_key

    cache = FemCache(root / "cache" / "fem")
    fem_tasks: dict[str, FemTask] = {}
    uses = pairs = 0
    fem_cached_keys, fem_all_keys = set(), set()
    todo_ids = {p.id for p in todo}
    for p in sweep.points:
        for i, s in enumerate(point_setups(sweep, p.values, root)):
            key = mechanics_key(s, sweep.file.benchmark.frames)
            pairs += 1
            fem_all_keys.add(key)
            if p.id not in todo_ids:
                continue
            uses += 1
            if cache.status(key):
                fem_cached_keys.add(key)
            else:
                fem_tasks.setdefault(key, FemTask(str(sweep.path), str(root), p.values, i))
    solved = 0
    if progress:
        progress("FEM solves", 0, len(fem_tasks))
    for _ in _map(run_fem_task, list(fem_tasks.values()), executor, workers, address):
        solved += 1
        if progress:
            progress("FEM solves", solved, len(fem_tasks))

    # 2. render and score, one task per distinct rendered set
    groups: dict[str, list] = {}
    for p in todo:
        groups.setdefault(render_key(sweep, p.values), []).append((pkeys[p.id], p.values))
    tasks = [RenderTask(str(sweep.path), str(root), k, tuple(v)) for k, v in groups.items()]
    done_now = frames_rendered = 0
    if progress:
        progress("points", resumed, len(sweep.points))
    for results in _map(run_render_task, tasks, executor, workers, address):
        done_now += len(results)
        frames_rendered += sum(r.get("rendered_now_frames", 0) for r in results)
        if progress:
            progress("points", resumed + done_now, len(sweep.points))

    # 3. the table and the report
    from transtac_sim.sweep.report import write_report

    rows = []
    for p in sweep.points:
        r = read_result(root, pkeys[p.id]) or {"status": "failed", "reason": "no result"}
        rows.append({"point": p.id, **{k: p.values[k] for k in p.values}, **{k: v for k, v in r.items() if k not in ("key", "values")}})
    failed = [{"point": r["point"], "reason": r.get("reason", "")} for r in rows if r["status"] != "done"]
    image_sets = len({render_key(sweep, p.values) for p in sweep.points})
    reuse = {
        "points": len(sweep.points), "motions": len(sweep.file.benchmark.motions),
        "fem_pairs_total": pairs, "fem_solves_total": len(fem_all_keys), "image_sets_total": image_sets,
        "points_sharing_images_total": len(sweep.points) - image_sets,
        "resumed_points": resumed,
        "fem_solves_run": solved, "fem_solves_from_cache": len(fem_cached_keys),
        "fem_uses": uses, "fem_shared": max(0, uses - solved - len(fem_cached_keys)),
        "rendered_sets": len(tasks), "frames_rendered_now": frames_rendered,
        "frames_per_set": len(sweep.file.benchmark.motions) * sweep.file.benchmark.frames,
        "points_scoring_shared_images": sum(len(v) - 1 for v in groups.values()),
    }
    table, md, html, plots = write_report(root, sweep, rows, reuse)
    write_json(root / "summary.json", {"sweep": sweep.file.name, "reuse": reuse, "failed": failed,
                                       "seconds": time.perf_counter() - t_start})
    return SweepReport(root, len(sweep.points), len(rows) - len(failed), failed, resumed, solved, len(fem_cached_keys),
                       reuse["fem_shared"], len(tasks), reuse["points_scoring_shared_images"], table, html, md, plots,
                       time.perf_counter() - t_start)


__all__ = ["LAYOUT_KEYS", "Point", "SweepReport", "run_sweep"]
