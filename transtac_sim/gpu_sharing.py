"""CUDA MPS (Multi-Process Service) for several ``generate`` workers on each GPU.

Without MPS the CUDA contexts of several processes on one GPU are time-sliced: one process's kernels run at a time.
Under MPS their kernels run side by side. The FEM's Newton iterations are many small launches that leave most of an
H100 idle, so that is where the workers gain: ``train_random``, 40 sequences, 8 workers on one H100 gave 4,064
labelled frames per hour under MPS against 3,431 without (BENCHMARKS.md ``generate_train_random_gpu_mps``).

``mps_server()`` starts NVIDIA's control daemon (``nvidia-cuda-mps-control -d``, part of the CUDA driver install)
for the duration of a ``with`` block, as the current user, and stops it at the end; a daemon that was already
running is used and left running. Processes that make their CUDA context inside the block (the local executor's
workers, Ray's actors on this machine) connect to it by themselves, through its default pipe directory.
Nothing about the GPU's settings is changed (no exclusive-process compute mode).
"""

from __future__ import annotations

import shutil
import subprocess
from collections.abc import Iterator
from contextlib import contextmanager

CONTROL = "nvidia-cuda-mps-control"


class MpsUnavailable(RuntimeError):
    """The MPS control daemon cannot be started here."""


@contextmanager
def mps_server() -> Iterator[bool]:
    """Runs the block under an MPS control daemon; yields True if this call started it (and so stops it)."""
    control = shutil.which(CONTROL)
    if control is None:
        raise MpsUnavailable(f"--mps: {CONTROL} is not on PATH (it comes with NVIDIA's CUDA driver; MPS needs an "
                             "NVIDIA GPU on this machine). Run without --mps.")
    started = subprocess.run([control, "-d"], capture_output=True, text=True)
    if started.returncode != 0 and "already running" not in (started.stdout + started.stderr):
        raise MpsUnavailable(f"--mps: `{CONTROL} -d` failed (exit {started.returncode}): "
                             f"{(started.stderr or started.stdout).strip()}")
    ours = started.returncode == 0
    try:
        yield ours
    finally:
        if ours:
            subprocess.run([control], input="quit\n", capture_output=True, text=True)
