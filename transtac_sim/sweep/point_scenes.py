"""The benchmark scenes of one sweep point (``sweep.config``): its hardware model (the sweep's own, or a copy with the
point's gel thickness and camera baseline), one Scene per benchmark motion with the point's markers, gel and cameras,
their SceneSetups with the point's stiffness, and the key of everything its rendered images depend on. ``sweep.run``
runs them.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import tomli_w

from transtac_sim.config import load_hardware
from transtac_sim.sweep.config import PIPELINE_KEYS, Sweep, indenter_mesh, key_of, layout_of


def hardware_ref(sweep: Sweep, values: dict, root: Path) -> str:
    """The hardware model of a point: the sweep's own, or a copy with the point's gel thickness and camera
    baseline written to ``root/hardware/<key>.toml``."""
    hw, _ = load_hardware(sweep.file.scene.hardware, sweep.path.parent)
    if values["thickness_mm"] == hw.gel.thickness_mm and values["baseline_mm"] == hw.cameras.baseline_mm:
        return sweep.file.scene.hardware
    d = hw.model_dump(mode="json", exclude_none=True)
    d["gel"]["thickness_mm"] = values["thickness_mm"]
    d["cameras"]["baseline_mm"] = values["baseline_mm"]
    path = root / "hardware" / f"{key_of(d)}.toml"
    if not path.is_file():
        from transtac_sim.writer.atomic import atomic_write

        text = (f"# written by transtac-sim sweep: {sweep.file.scene.hardware} with another gel thickness or "
                "baseline\n")
        atomic_write(path, lambda f: f.write((text + tomli_w.dumps(d)).encode()))
    return str(path)


def motion_scenes(sweep: Sweep, values: dict, root: Path) -> list:
    """The point's benchmark: one Scene per motion, with the point's markers, gel and cameras."""
    from transtac_sim.config.scene import Scene

    b, base = sweep.file.benchmark, sweep.file.scene
    hw, _ = load_hardware(base.hardware, sweep.path.parent)
    layout = layout_of(values, tuple(hw.gel.size_mm))
    scenes = []
    for i, m in enumerate(b.motions):
        if m.kind == "press":
            traj = [{"kind": "press", "depth_mm": b.press_depth_mm, "frames": b.frames}]
        else:
            n_press = max(1, b.frames // 2)
            traj = [{"kind": "press", "depth_mm": b.press_depth_mm, "frames": n_press},
                    {"kind": m.kind, "direction_deg": m.direction_deg, "distance_mm": m.distance_mm,
                     "frames": b.frames - n_press}]
        mesh = indenter_mesh(m.indenter, sweep.path)
        scenes.append(Scene.model_validate({
            "name": f"{sweep.file.name}_{i}_{m.kind}_{mesh.stem}", "seed": sweep.file.seed,
            "sensor": {"hardware": hardware_ref(sweep, values, root), "markers": layout.model_dump()},
            "mesh": base.mesh.model_dump(), "physics": base.physics.model_dump(), "render": base.render.model_dump(),
            "indenters": [{"name": mesh.stem, "mesh": str(mesh), "units": "mm", "start_xy_mm": m.start_xy_mm,
                           "start_gap_mm": 0.2, "friction": m.friction, "trajectory": traj}],
            "outputs": {"cameras": ["left", "right"], "illuminations": ["uv"], "aovs": [], "labels": True},
        }))
    return scenes


def point_setups(sweep: Sweep, values: dict, root: Path) -> list:
    """The SceneSetup of every benchmark motion of a point (stiffness applied to the gel material)."""
    from transtac_sim.scene_setup import build_setup

    setups = []
    for scene in motion_scenes(sweep, values, root):
        setup = build_setup(scene, sweep.path)
        if values.get("youngs_modulus_mpa") is not None:
            gel = setup.sensor.gel.model_copy(update={"youngs_modulus_mpa": float(values["youngs_modulus_mpa"])})
            setup = dataclasses.replace(setup, sensor=dataclasses.replace(setup.sensor, gel=gel))
        setups.append(setup)
    return setups


def render_key(sweep: Sweep, values: dict) -> str:
    """Everything the rendered images depend on: all but the pipeline settings."""
    f = sweep.file
    return key_of({"values": {k: v for k, v in values.items() if k not in PIPELINE_KEYS}, "seed": f.seed,
                   "benchmark": f.benchmark.model_dump(mode="json"), "scene": f.scene.model_dump(mode="json")})
