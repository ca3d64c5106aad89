"""``local_tasks`` spreads its workers over the machine's GPUs (``CUDA_VISIBLE_DEVICES`` set per worker before any CUDA
context), and ``visible_gpus`` finds them without making a context."""

from __future__ import annotations

import os
import time
from collections import Counter
from pathlib import Path

from transtac_sim.executors import local_tasks, visible_gpus


def _worker_device(_task=None) -> tuple[int, str | None]:
    time.sleep(0.5)  # long enough that every worker takes tasks
    return os.getpid(), os.environ.get("CUDA_VISIBLE_DEVICES")


def test_local_workers_take_the_gpus_in_turn():
    """4 workers on GPUs "3" and "5": each worker keeps one of them, and each GPU gets two workers."""
    results = list(local_tasks(_worker_device, [None] * 12, 4, spawn=True, gpus=["3", "5"]))
    seen = dict(results)
    assert all(seen[pid] == device for pid, device in results)  # a worker keeps its GPU
    assert set(seen.values()) == {"3", "5"}
    counts = Counter(seen.values())
    assert max(counts.values()) - min(counts.values()) <= 1, seen
    # without gpus a worker's CUDA_VISIBLE_DEVICES is what it inherited
    inherited = os.environ.get("CUDA_VISIBLE_DEVICES")
    assert {device for _, device in local_tasks(_worker_device, [None] * 4, 2, spawn=True)} == {inherited}


def test_visible_gpus(tmp_path: Path, monkeypatch):
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1, 3")
    assert visible_gpus() == ["1", "3"]
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert visible_gpus() == []
    monkeypatch.delenv("CUDA_VISIBLE_DEVICES")
    monkeypatch.setenv("PATH", str(tmp_path))  # no nvidia-smi: no NVIDIA driver here
    assert visible_gpus() == []
    smi = tmp_path / "nvidia-smi"
    smi.write_text('#!/bin/sh\necho "GPU 0: NVIDIA H200 (UUID: a)"\necho "GPU 1: NVIDIA H200 (UUID: b)"\n')
    smi.chmod(0o755)
    assert visible_gpus() == ["0", "1"]
