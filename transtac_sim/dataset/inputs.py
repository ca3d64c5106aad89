"""The files a scene refers to (hardware model, its materials, a marker layout file, indenter meshes) and their
content (sha256): part of a dataset's identity (``inputs`` in manifest.json), so that a run resumed after one of
them changed is refused instead of mixing frames of the old and the new sensor in one dataset."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from transtac_sim.config import ConfigError, Scene, load_hardware
from transtac_sim.config.hardware import FileLayout
from transtac_sim.config.loader import resolve_named_file


def input_files(scene: Scene, scene_path: Path) -> dict[str, Path]:
    """Each file ``scene`` (read from ``scene_path``) uses, by the key that names it (``sensor.hardware``, the
    hardware model's ``gel.material`` ..., ``markers.path``, ``indenters[i].mesh``,
    ``randomize.indenter_meshes[i]``), resolved as ``scene_setup.build_setup`` resolves it."""
    here = Path(scene_path).parent
    hw, hw_path = load_hardware(scene.sensor.hardware, here)
    files = {"sensor.hardware": hw_path}
    for key, name in (("gel.material", hw.gel.material), ("backing.material", hw.backing.material),
                      ("housing.material", hw.housing.material), ("markers.pigment", hw.markers.pigment)):
        files[key] = resolve_named_file(name, "materials", hw_path.parent)
    layout, base = (scene.sensor.markers, here) if scene.sensor.markers else (hw.markers.arrangement, hw_path.parent)
    if isinstance(layout, FileLayout):
        files["markers.path"] = base / layout.path
    for i, indenter in enumerate(scene.indenters):
        files[f"indenters[{i}].mesh"] = here / indenter.mesh
    for i, mesh in enumerate(scene.randomize.indenter_meshes if scene.randomize and scene.indenters else []):
        files[f"randomize.indenter_meshes[{i}]"] = here / mesh
    return files


def fingerprint(scene: Scene, scene_path: Path) -> dict[str, dict[str, str]]:
    """``{key: {"file": its path relative to the scene file's folder, "sha256": hex digest of its bytes}}`` of
    ``input_files`` (relative, so that the same scene gives the same manifest wherever the project lies); a file that
    cannot be read is a ConfigError naming the scene file and the key."""
    here = Path(scene_path).resolve().parent
    out = {}
    for key, path in input_files(scene, scene_path).items():
        try:
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
        except OSError as e:
            raise ConfigError(scene_path, [(key, f"{path}: cannot be read ({e.strerror})")]) from None
        out[key] = {"file": os.path.relpath(path.resolve(), here), "sha256": digest}
    return out


def changed_inputs(old: dict, new: dict) -> list[str]:
    """The inputs of ``new`` whose content differs from ``old`` (a manifest's ``inputs``), as ``key (file)``,
    and those of ``old`` that this run no longer uses."""
    def digest(entry) -> str | None:
        return entry.get("sha256") if isinstance(entry, dict) else None

    changed = [f"{k} ({v['file']})" for k, v in new.items() if digest(old.get(k)) != v["sha256"]]
    return changed + [f"{k} (no longer used)" for k in old if k not in new]
