"""Helpers of the rendering benchmark scripts: the machine's description and markdown tables (the
BENCHMARKS.md sections are written by ``scripts/benchmarks_md.update_section``)."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path


def machine(variant: str) -> str:
    """'2-core CPU (model)' for llvm variants, the GPU's name for cuda variants."""
    if variant.startswith("cuda"):
        try:
            name = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                                  text=True, timeout=10).stdout.strip().splitlines()[0]
        except (OSError, IndexError, subprocess.SubprocessError):
            name = "unknown GPU"
        return f"GPU {name}"
    model = platform.processor() or "unknown"
    try:
        model = next(line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                     if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{os.cpu_count()}-core CPU ({model})"


def markdown_table(header: list[str], rows: list[list]) -> str:
    def fmt(x):
        return f"{x:.4g}" if isinstance(x, float) else str(x)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(fmt(x) for x in r) + " |" for r in rows])
