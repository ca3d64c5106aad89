"""Independent tasks on Ray (``generate`` sequences, ``sweep`` points): results as the tasks finish."""

from __future__ import annotations

from collections.abc import Callable, Iterator


def start_ray(address: str | None, workers: int):
    """The ``ray`` module, connected to the cluster at ``address`` or to a local Ray with ``workers`` CPUs."""
    import ray

    if not ray.is_initialized():
        ray.init(address=address, num_cpus=None if address else max(1, workers), include_dashboard=False,
                 log_to_driver=False, ignore_reinit_error=True)
    return ray


def ray_tasks(fn: Callable, tasks: list, address: str | None, workers: int) -> Iterator:
    """``fn(task)`` for each task as a Ray task (as many at once as the cluster has CPUs), in order of completion."""
    ray = start_ray(address, workers)
    remote = ray.remote(fn)
    pending = [remote.remote(t) for t in tasks]
    while pending:
        ready, pending = ray.wait(pending, num_returns=1)
        yield ray.get(ready[0])
