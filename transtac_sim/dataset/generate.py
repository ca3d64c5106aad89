"""``transtac-sim generate``: scene file -> dataset folder (DESIGN.md section 4).

Sequences are the unit of work (frames within one warm-start from each other); they run inline, in local
worker processes, or as Ray tasks, and each writes its frames itself, atomically, labels.json last. The
main process writes manifest.json before the first frame (the run's identity: the resolved scene and the content
of every file it uses) and again at the end with every frame's status, then the COCO files and a contact sheet.
Re-running the same command skips every complete frame (re-solving physics of an unfinished sequence from its
start, so warm starts match; a frame damaged since it was written is written again) and gives the same bytes as
an uninterrupted run, wall-clock fields aside.

The output folder must be new, empty, or a dataset of this same scene, seed, frame count and input files
(``check_out_folder``); anything else is refused before a file is written.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

from transtac_sim.config import ConfigError, load_scene
from transtac_sim.dataset.coco import write_coco
from transtac_sim.dataset.inputs import changed_inputs, fingerprint
from transtac_sim.dataset.manifest import build_manifest, read_manifest, write_manifest
from transtac_sim.executors import (
    limit_threads,
    local_tasks,
    ray_node_threads,
    ray_tasks,
    start_ray,
    visible_gpus,
)
from transtac_sim.gpu_sharing import MpsUnavailable, mps_server
from transtac_sim.writer.atomic import write_json


@dataclass(frozen=True)
class SequenceTask:
    scene_path: str
    scene_json: str  # the resolved scene (seed and frame limit applied)
    index: int
    root: str
    retry_failed: bool = False  # solve a sequence again even where an earlier run recorded its failure


@dataclass
class GenerateReport:
    root: Path
    frames_done: int
    frames_failed: list[dict]
    frames_skipped: int
    timings: dict[str, float]
    stages_run: list[str]
    coco_images: dict[str, int]
    contact_sheet: Path | None
    seconds: float = 0.0
    frames_redone: list[str] = field(default_factory=list)  # "<sequence>/<frame>: why": damaged, written again
    gpus_used: list[str] = field(default_factory=list)  # Ray ids of the GPUs that solved sequences (Ray on GPUs)


def _run_task(task: SequenceTask) -> list[dict]:
    from transtac_sim.dataset.sequence import run_sequence

    return run_sequence(task)


def _run_local(tasks: list[SequenceTask], workers: int) -> Iterator[list[dict]]:
    # spawned, not forked: a forked CUDA context is unusable. The workers take the machine's GPUs in turn, one each;
    # several workers on one GPU each open a context there, time-sliced unless they run under MPS (gpu_sharing.py)
    return local_tasks(_run_task, tasks, workers, spawn=True, gpus=visible_gpus())


def _run_ray(tasks: list[SequenceTask], address: str | None, workers: int, gpus_used: set[str]) -> Iterator[list[dict]]:
    """Sequences on Ray. Without GPUs each sequence is a task (as many run at once as the cluster has CPUs).
    With G GPUs each of G x ceil(workers / G) actors holds 1 / ceil(workers / G) of a GPU (Ray sets its
    CUDA_VISIBLE_DEVICES) and solves sequences one after another: every GPU is used, ``workers`` = 2 G puts two on
    each, so that one renders while the other solves (on one H100 two workers gave 1.38x the frames per hour of
    one, BENCHMARKS.md ``generate_train_random_gpu_spmv``), and a worker keeps its GPU, its CUDA context and its
    loaded kernels from one sequence to the next. Adds the Ray ids of the GPUs that solved sequences to
    ``gpus_used``."""
    from ray.util import ActorPool

    ray = start_ray(address, workers)
    gpus = int(ray.cluster_resources().get("GPU", 0))
    if not gpus:
        yield from ray_tasks(_run_task, tasks, address, workers)
        return
    share = ray_gpu_share(gpus, workers)
    actor = ray.remote(num_gpus=share, num_cpus=0)(_SequenceWorker)
    pool = ActorPool([actor.remote(share) for _ in range(round(gpus / share))])
    for gpu_ids, frames in pool.map_unordered(lambda a, t: a.run.remote(t), tasks):
        gpus_used.update(gpu_ids)
        yield frames


class _SequenceWorker:
    """A Ray actor that solves sequences on the GPU share it was given, its thread pools limited to the same share of
    its node's cores (``executors.ray_node_threads``)."""

    def __init__(self, gpu_share: float):
        limit_threads(ray_node_threads(gpu_share))

    def run(self, task: SequenceTask) -> tuple[list[str], list[dict]]:
        """(the Ray ids of this actor's GPUs, the sequence's frame statuses)"""
        import ray

        return [str(i) for i in ray.get_gpu_ids()], _run_task(task)


def ray_gpu_share(gpus: float, workers: int) -> float:
    """The GPU share of one sequence task: 1 while there are no more workers than GPUs, else 1 / (workers per
    GPU, rounded up) (Ray packs tasks whose shares add up to at most 1 onto one GPU)."""
    per_gpu = -(-max(1, workers) // max(1, int(gpus)))
    return 1.0 / per_gpu


def scene_differences(old, new, shown: int = 4) -> str:
    """The resolved scene's entries (dotted keys) whose values differ between a dataset's manifest (``old``) and this
    run (``new``), as "key: old -> new", the first ``shown`` of them (a default that changed between versions of this
    package shows up here too, e.g. physics.newton_force_rtol)."""
    def flat(value, prefix=""):
        if isinstance(value, dict):
            return {k: v for key, item in value.items() for k, v in flat(item, f"{prefix}{key}.").items()}
        return {prefix.rstrip("."): value}

    a, b = flat(old if isinstance(old, dict) else {}), flat(new)
    keys = sorted(k for k in a.keys() | b.keys() if a.get(k, "unset") != b.get(k, "unset"))
    listed = [f"{k}: {json.dumps(a.get(k, 'unset'))} -> {json.dumps(b.get(k, 'unset'))}" for k in keys[:shown]]
    return "; ".join(listed) + (f"; and {len(keys) - shown} more" if len(keys) > shown else "")


def check_out_folder(root: Path, resolved: dict, inputs: dict) -> dict | None:
    """The manifest of the dataset at ``root`` where this run may resume it; None where ``root`` is new or empty.
    Anything else raises a ConfigError (nothing is written): ``root`` is a file, holds files but no manifest (not a
    dataset, or the frames of a run that recorded no identity), a dataset of another scene, seed or frame count
    (``resolved``), or one made from files whose content has changed since (``inputs``)."""
    if root.exists() and not root.is_dir():
        raise ConfigError(root, [("", "exists and is not a folder; choose another --out (nothing was changed)")])
    old = read_manifest(root)
    if old is None:
        if root.is_dir() and any(root.iterdir()):
            raise ConfigError(root, [("", _not_a_dataset(root))])
        return None
    if old.get("scene") != resolved:
        raise ConfigError(root / "manifest.json", [("scene", "this folder holds a dataset of another scene, seed or "
                                                    f"frame count ({scene_differences(old.get('scene'), resolved)}); "
                                                    "choose another --out (nothing was changed)")])
    if not isinstance(old.get("inputs"), dict):
        raise ConfigError(root / "manifest.json", [("inputs", "missing (made by an earlier version of transtac_sim): "
                                                    "whether its hardware model, materials and meshes are unchanged "
                                                    "cannot be checked; choose another --out (nothing was changed)")])
    if changed := changed_inputs(old["inputs"], inputs):
        why = (f"files this dataset was made from have changed since: {'; '.join(changed)} (paths from the scene "
               "file's folder); resuming would mix frames made from the old and the new files: choose another --out, "
               "or restore them (nothing was changed)")
        raise ConfigError(root / "manifest.json", [("inputs", why)])
    return old


def _not_a_dataset(root: Path) -> str:
    """Why a non-empty ``root`` without manifest.json is refused, and what to do."""
    if (root / "sequences").exists():
        return ("holds dataset frames (sequences/) but no manifest.json: which scene, seed and files they were made "
                "from cannot be checked (a run interrupted before it wrote one, or files copied in); choose a new "
                f"--out, or delete {root} to start over (nothing was changed)")
    return "is not empty and holds no dataset (no manifest.json); choose a new or empty --out (nothing was changed)"


def _make_folder(root: Path) -> None:
    """Create ``root`` (and its parents); a path that cannot be a folder is a ConfigError naming it."""
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        why = f"cannot create the dataset folder ({e.strerror}); choose another --out"
        raise ConfigError(root, [("", why)]) from None


def generate(scene_path: str | Path, out: str | Path, *, frames: int | None = None, seed: int | None = None,
             sequences: int | None = None, workers: int = 1, executor: str = "local", address: str | None = None,
             on_frames: Callable[[int, int], None] | None = None, retry_failed: bool = False,
             mps: bool = False) -> GenerateReport:
    """Generate (or resume) the dataset of ``scene_path`` in ``out``; ``on_frames(done, total)`` reports
    progress after each sequence. A resumed run keeps the failures an earlier run recorded (their sequences are
    not solved again) unless ``retry_failed``. ``mps``: the workers share each GPU through CUDA MPS
    (gpu_sharing.py; raises ``MpsUnavailable`` where it cannot be started) on this machine: the local executor's, or
    the Ray actors where no ``address`` is given (a Ray instance on this machine, which ``ray.init`` starts or finds;
    on two H200s, 16 workers under MPS gave 1.74x the frames per hour of the local executor's 8 on one, BENCHMARKS.md
    ``generate_train_random_gpu_ray_two_gpus_mps``)."""
    t0 = time.perf_counter()
    if mps and executor != "local" and address is not None:
        raise MpsUnavailable("--mps starts CUDA MPS on this machine only (the local executor, or Ray without "
                             "--address): a Ray cluster's workers outlive this command, so drop --mps and start the "
                             "MPS daemon (nvidia-cuda-mps-control -d) on its GPU nodes yourself, or drop --address")
    scene_path = Path(scene_path).resolve()
    scene = load_scene(scene_path)
    upd = {k: v for k, v in (("seed", seed), ("sequences", sequences)) if v is not None}
    scene = scene.model_copy(update=upd)
    # a trajectory has its own length; a contact-free scene repeats its rest state as often as asked
    limit = (min(frames, scene.frame_count) if scene.indenters else frames) if frames else scene.frame_count
    root = Path(out)
    resolved = json.loads(scene.model_dump_json())
    resolved["frames_per_sequence"] = limit
    from transtac_sim.scene_setup import build_setup

    base = build_setup(scene, scene_path)  # every referenced file is checked before anything is written
    inputs = fingerprint(scene, scene_path)
    old = check_out_folder(root, resolved, inputs)
    # MPS is started before anything is written: where it cannot be, the folder is left as it was
    with mps_server() if mps else nullcontext():
        _make_folder(root)
        if old is None:
            write_manifest(root, build_manifest(resolved, str(scene_path), scene.seed, [], [], {}, inputs))
        write_json(root / "calibration.json", base.sensor.calibration_json())
        tasks = [SequenceTask(str(scene_path), json.dumps(resolved), i, str(root), retry_failed)
                 for i in range(scene.sequences)]
        results: list[dict] = []
        total = len(tasks) * limit
        gpus_used: set[str] = set()
        runs = _run_ray(tasks, address, workers, gpus_used) if executor == "ray" else _run_local(tasks, workers)
        for frames_of_sequence in runs:
            results += frames_of_sequence
            if on_frames:
                on_frames(len(results), total)
    timings: dict[str, float] = {}
    stages: set[str] = set()
    for r in results:
        for k, v in r.pop("timings", {}).items():
            timings[k] = timings.get(k, 0.0) + v
        stages |= set(r.pop("stages", []))
    samples = [{k: r[k] for k in ("sequence", "frame", "status", "reason") if k in r} for r in results]
    manifest = build_manifest(resolved, str(scene_path), scene.seed, samples, sorted(stages), timings, inputs)
    done = [(s["sequence"], s["frame"]) for s in manifest["samples"] if s["status"] == "done"]
    coco = {}
    if "uv" in scene.outputs.illuminations and scene.outputs.labels:
        coco = write_coco(root, done, list(scene.outputs.cameras), base.sensor.cameras["left"].image_size, scene.seed)
    write_manifest(root, manifest)
    from transtac_sim.dataset.sheet import dataset_contact_sheet

    sheet = dataset_contact_sheet(root, done, scene.outputs, seed=scene.seed)
    failed = [s for s in manifest["samples"] if s["status"] == "failed"]
    redone = [f"{r['sequence']}/{r['frame']:06d}: {r['redone']}" for r in results if "redone" in r]
    return GenerateReport(root, len(done), failed, sum(r.get("skipped", False) for r in results), timings,
                          sorted(stages), coco, sheet, time.perf_counter() - t0, redone, sorted(gpus_used))
