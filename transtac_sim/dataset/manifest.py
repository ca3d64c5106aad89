"""``manifest.json``: what a dataset is and how it was made.

Keys: ``format_version``, ``generator`` (package and version), ``scene`` (the resolved scene config),
``scene_file``, ``seed``, ``samples`` (one per frame: sequence, frame, status ``done`` | ``failed``,
reason), ``stages_run``, ``timings`` (seconds per stage, summed), ``software`` (versions), ``machine``.
"""

from __future__ import annotations

import json
import os
import platform
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from transtac_sim import __version__
from transtac_sim.dataset import contract
from transtac_sim.writer.atomic import write_json

SOFTWARE = ("numpy", "scipy", "warp-lang", "mitsuba", "drjit", "pytetwild", "trimesh", "opencv-contrib-python-headless")


def software_versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for name in SOFTWARE:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


def machine() -> dict:
    return {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
            "cpu_count": os.cpu_count()}


def build_manifest(scene: dict, scene_file: str, seed: int, samples: list[dict], stages_run: list[str],
                   timings: dict[str, float]) -> dict:
    return {
        "format_version": contract.FORMAT_VERSION,
        "generator": {"name": "transtac_sim", "version": __version__},
        "scene_file": scene_file,
        "seed": seed,
        "scene": scene,
        "samples": sorted(samples, key=lambda s: (s["sequence"], s["frame"])),
        "stages_run": sorted(stages_run),
        "timings": {k: round(v, 4) for k, v in sorted(timings.items())},
        "software": software_versions(),
        "machine": machine(),
    }


def read_manifest(root: Path) -> dict | None:
    p = Path(root) / "manifest.json"
    return json.loads(p.read_text()) if p.is_file() else None


def write_manifest(root: Path, manifest: dict) -> Path:
    return write_json(Path(root) / "manifest.json", manifest)
