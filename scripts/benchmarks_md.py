"""Shared by the benchmark scripts: the machine's name and BENCHMARKS.md sections.

Each script owns one section between ``<!-- BEGIN name -->`` and ``<!-- END name -->`` and replaces only
that one, so results of different scripts and machines live side by side. A section measured on another
machine (the GPU machine) comes back as a file: ``python scripts/benchmarks_md.py SECTION FILE``.
"""

from __future__ import annotations

import os
import platform
import re
from pathlib import Path

import typer


def machine_name(device: str = "cpu") -> str:
    """``2-core CPU (x86_64)`` or the GPU's name for a CUDA device."""
    if device.startswith("cuda"):
        for name_of in (_warp_name, _torch_name):
            try:
                return f"GPU {name_of(device)}"
            except Exception:  # that framework is not installed here, or sees no GPU
                continue
        return "GPU"
    return f"{os.cpu_count()}-core CPU ({platform.machine()})"


def _warp_name(device: str) -> str:
    import warp as wp

    return wp.get_device(device).name


def _torch_name(device: str) -> str:
    import torch

    return f"{torch.cuda.get_device_name(torch.device(device))} (torch {torch.__version__})"


def update_section(path: Path, name: str, markdown: str) -> None:
    begin, end = f"<!-- BEGIN {name} -->", f"<!-- END {name} -->"
    text = path.read_text() if path.exists() else "# Benchmarks\n"
    block = f"{begin}\n{markdown.strip()}\n{end}"
    if begin in text and end in text:
        text = re.sub(re.escape(begin) + r".*?" + re.escape(end), lambda _: block, text, flags=re.S)
    else:
        text = text.rstrip() + f"\n\n## {name}\n\n{block}\n"
    path.write_text(text)


def publish(markdown: str, md_out: Path | None, benchmarks: bool, section: str) -> None:
    """A benchmark script's table: printed, written to ``md_out`` where given, and with ``benchmarks`` into
    BENCHMARKS.md's ``section``."""
    print(markdown)
    if md_out:
        md_out.write_text(markdown + "\n")
    if benchmarks:
        update_section(Path(__file__).resolve().parents[1] / "BENCHMARKS.md", section, markdown)


def _store(section: str = typer.Argument(..., help="the BENCHMARKS.md section's name"),
           markdown: Path = typer.Argument(..., exists=True, dir_okay=False, help="a file with the section's body")) -> None:
    """Writes a section measured elsewhere (a GPU) into BENCHMARKS.md."""
    update_section(Path(__file__).resolve().parents[1] / "BENCHMARKS.md", section, markdown.read_text())


if __name__ == "__main__":  # python scripts/benchmarks_md.py SECTION FILE
    typer.run(_store)
