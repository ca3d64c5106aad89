"""``manifest.json``: what a dataset is and how it was made.

Keys: ``format_version``, ``generator`` (package and version), ``scene`` (the resolved scene config),
``inputs`` (the files the scene uses: key -> file and sha256, ``dataset/inputs.py``), ``scene_file``, ``seed``,
``samples`` (one per frame: sequence, frame, status ``done`` | ``failed``, reason), ``stages_run``, ``timings``
(seconds per stage, summed), ``software`` (versions), ``machine``.

``generate`` writes it before the first frame, with no samples (the run's identity: ``scene`` and ``inputs``, what
a resumed run is checked against), and again, complete, at the end.
"""

from __future__ import annotations

import json
import os
import platform
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from transtac_sim import __version__
from transtac_sim.config import ConfigError
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
                   timings: dict[str, float], inputs: dict) -> dict:
    return {
        "format_version": contract.FORMAT_VERSION,
        "generator": {"name": "transtac_sim", "version": __version__},
        "scene_file": scene_file,
        "seed": seed,
        "scene": scene,
        "inputs": inputs,
        "samples": sorted(samples, key=lambda s: (s["sequence"], s["frame"])),
        "stages_run": sorted(stages_run),
        "timings": {k: round(v, 4) for k, v in sorted(timings.items())},
        "software": software_versions(),
        "machine": machine(),
    }


def read_manifest(root: Path) -> dict | None:
    """The manifest of the dataset at ``root``, None where there is none; one that cannot be read (cut short,
    not JSON, not an object) is a ConfigError naming it and what to do."""
    p = Path(root) / "manifest.json"
    if not p.is_file():
        return None
    try:
        manifest = json.loads(p.read_text())
    except (OSError, ValueError) as e:  # ValueError: JSON cut short or not UTF-8
        manifest, why = None, str(e)
    else:
        why = "not a JSON object"
    if isinstance(manifest, dict):
        return manifest
    raise ConfigError(p, [("", f"unreadable ({why}); it records which scene and files this dataset was made from, so "
                               f"it cannot be resumed: restore the file, or choose another --out, or delete {root} "
                               "to start over (nothing was changed)")])


def write_manifest(root: Path, manifest: dict) -> Path:
    return write_json(Path(root) / "manifest.json", manifest)
