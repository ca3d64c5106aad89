"""A scene file resolved into everything the stages need: the sensor, and each indenter's checked mesh
and start pose. This is where references between files (hardware model, materials, meshes) are
followed and checked, so that a bad file fails here with its name, before any solver runs."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from transtac_sim.config import ConfigError, Scene, load_scene
from transtac_sim.config.loader import resolve_named_file
from transtac_sim.config.scene import Indenter
from transtac_sim.indenters.loading import IndenterMesh, IndenterMeshError, load_indenter_mesh
from transtac_sim.indenters.placement import start_pose
from transtac_sim.sensor.assembly import Sensor, build_sensor


@dataclass(frozen=True)
class PlacedIndenter:
    config: Indenter
    mesh: IndenterMesh
    start_pose: np.ndarray  # 4x4, indenter frame -> gel frame, mm


@dataclass(frozen=True)
class SceneSetup:
    scene: Scene
    path: Path
    sensor: Sensor
    indenters: list[PlacedIndenter]

    @property
    def has_contact(self) -> bool:
        """Whether any indenter can touch the gel: one that starts above the surface and only holds never does."""
        return any(i.config.start_gap_mm <= 0 or any(s.kind != "hold" for s in i.config.trajectory)
                   for i in self.indenters)


def load_setup(path: str | Path) -> SceneSetup:
    """Load ``path`` and everything it refers to; raises ConfigError naming the file and key at fault."""
    path = Path(path).resolve()
    return build_setup(load_scene(path), path)


def build_setup(scene: Scene, path: Path, *, marker_seed: int | None = None) -> SceneSetup:
    """Resolve ``scene`` (read from ``path``: relative references start there); ``marker_seed`` replaces
    the marker layout's seed (domain randomisation)."""
    try:  # a hardware model that is not there is the scene's mistake: name its key
        resolve_named_file(scene.sensor.hardware, "hardware_models", path.parent)
    except FileNotFoundError as e:
        raise ConfigError(path, [("sensor.hardware", str(e))]) from None
    sensor = build_sensor(scene.sensor.hardware, scene.sensor.markers, layout_source=path, relative_to=path.parent,
                          marker_seed=marker_seed)
    if problems := scene.depth_problems(sensor.hardware.gel.thickness_mm):
        raise ConfigError(path, problems)
    if not scene.render.distortion:  # the recorded images are ideal pinhole images: say so in the calibration
        sensor = replace(sensor, cameras={k: replace(c, dist=np.zeros_like(c.dist)) for k, c in sensor.cameras.items()})
    placed = []
    for i, cfg in enumerate(scene.indenters):
        key = f"indenters[{i}]"
        try:
            mesh = load_indenter_mesh(path.parent / cfg.mesh, cfg.units)
        except IndenterMeshError as e:
            raise ConfigError(path, [(f"{key}.mesh", str(e))]) from None
        placed.append(PlacedIndenter(cfg, mesh, start_pose(cfg, mesh, sensor.gel_size_mm, source=str(path), key=key)))
    return SceneSetup(scene, path, sensor, placed)
