"""Independent tasks (``generate`` sequences, ``sweep`` points) in local worker processes or on Ray: results as the
tasks finish."""

from __future__ import annotations

import multiprocessing
import os
import shutil
import subprocess
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed


def limit_threads(threads: int) -> None:
    """A local worker's start: each thread pool of the process (BLAS, OpenMP, OpenCV's) gets ``threads`` threads, so
    that K workers on C cores run about C threads in their CPU stages, not K x C that wait on each other (on an H100
    machine with 16 cores, 8 ``generate`` workers made 1.63x the frames per hour with it, BENCHMARKS.md
    ``generate_train_random_gpu_worker_threads``)."""
    import cv2
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=threads)
    cv2.setNumThreads(threads)


def visible_gpus() -> list[str]:
    """The CUDA devices this process may use, as ``CUDA_VISIBLE_DEVICES`` names them: that variable's entries where it
    is set, else one index per GPU that ``nvidia-smi -L`` lists; [] without an NVIDIA driver. Makes no CUDA context."""
    listed = os.environ.get("CUDA_VISIBLE_DEVICES")
    if listed is not None:
        return [d.strip() for d in listed.split(",") if d.strip()]
    smi = shutil.which("nvidia-smi")
    if smi is None:
        return []
    try:
        out = subprocess.run([smi, "-L"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(i) for i, line in enumerate(line for line in out.splitlines() if line.startswith("GPU "))]


def _start_worker(threads: int, gpus: list[str], started) -> None:
    """A local worker's start: its thread pools (``limit_threads``) and, with ``gpus``, the next of them in turn
    (``started``: a shared count of the workers started) as its only CUDA device, set before any CUDA context is
    made."""
    limit_threads(threads)
    if gpus:
        with started.get_lock():
            index = started.value
            started.value += 1
        os.environ["CUDA_VISIBLE_DEVICES"] = gpus[index % len(gpus)]


def local_tasks(fn: Callable, tasks: list, workers: int, spawn: bool = False,
                gpus: list[str] | None = None) -> Iterator:
    """``fn(task)`` for each task, in order of completion: inline with one worker, else in ``workers`` processes
    (``spawn``: started fresh rather than forked, which a process holding a CUDA context needs) whose thread pools
    share the cores (``limit_threads``). With ``gpus`` (``CUDA_VISIBLE_DEVICES`` names) the workers take them in turn,
    one each, so that a machine's GPUs share the workers."""
    if workers <= 1:
        yield from map(fn, tasks)
        return
    threads = max(1, (os.cpu_count() or 1) // workers)
    context = multiprocessing.get_context("spawn") if spawn else multiprocessing.get_context()
    started = context.Value("i", 0)
    with ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_start_worker,
                             initargs=(threads, list(gpus or []), started)) as pool:
        for fut in as_completed([pool.submit(fn, t) for t in tasks]):
            yield fut.result()


def start_ray(address: str | None, workers: int):
    """The ``ray`` module, connected to the cluster at ``address`` or to a local Ray with ``workers`` CPUs."""
    import ray

    if not ray.is_initialized():
        ray.init(address=address, num_cpus=None if address else max(1, workers), include_dashboard=False,
                 log_to_driver=False, ignore_reinit_error=True)
    return ray


def ray_node_threads(gpu_share: float = 0.0) -> int:
    """Inside a Ray worker: its share of its node's cores, for ``limit_threads`` (at least 1). A task holding one of
    the node's Ray CPUs gets cores / Ray CPUs; an actor holding ``gpu_share`` of a GPU gets cores x gpu_share / the
    node's GPUs (Ray itself sets OMP_NUM_THREADS only, not the BLAS or OpenCV pools)."""
    import ray

    here = ray.get_runtime_context().get_node_id()
    resources = next((n["Resources"] for n in ray.nodes() if n["NodeID"] == here), {})
    cores = os.cpu_count() or 1
    if gpu_share > 0.0:
        return max(1, int(cores * gpu_share / max(resources.get("GPU", 1.0), 1.0)))
    return max(1, int(cores / max(resources.get("CPU", 1.0), 1.0)))


def _on_node_share(fn: Callable, task):
    limit_threads(ray_node_threads())
    return fn(task)


def ray_tasks(fn: Callable, tasks: list, address: str | None, workers: int) -> Iterator:
    """``fn(task)`` for each task as a Ray task (as many at once as the cluster has CPUs, each task's thread pools
    limited to its share of its node's cores), in order of completion."""
    ray = start_ray(address, workers)
    remote = ray.remote(_on_node_share)
    pending = [remote.remote(fn, t) for t in tasks]
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        yield ray.get(ready[0])
