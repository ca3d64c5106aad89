"""Indenters are placed by their shape (anchor = "footprint") or by their mesh origin (anchor = "origin"), and
a frame that presses an indenter in without touching the gel is refused, naming the frame and the indenter.

The awkward case is a CAD file whose origin lies 24 mm from its body: pressed at start_xy_mm = [0, 0] by
its origin it would miss the tiny sensor's 32 x 24 mm gel entirely."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from conftest import REPO
from typer.testing import CliRunner

from transtac_sim.cli import app
from transtac_sim.config import ConfigError
from transtac_sim.config.scene import Indenter
from transtac_sim.indenters.library import LIBRARY
from transtac_sim.indenters.loading import load_indenter_mesh
from transtac_sim.indenters.placement import start_pose
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import PRESSED_MM, SimulationFailed, check_pressed_indenters_touch

BODY_OFFSET_MM = np.array([0.0, -24.0, 0.0])  # where the body lies in its own file's frame
RADIUS_MM = 2.0


def _scene(tmp_path: Path, anchor: str | None, start_xy=(1.0, 2.0), depth_mm: float = 0.5) -> Path:
    """A scene on the tiny sensor with one sphere whose STL origin lies 24 mm from its centre."""
    body = trimesh.creation.icosphere(subdivisions=3, radius=RADIUS_MM)
    body.apply_translation(BODY_OFFSET_MM)
    body.export(tmp_path / "cad_part.stl")
    anchor_line = f'anchor = "{anchor}"\n' if anchor else ""
    scene = tmp_path / f"off_origin_{anchor}.toml"
    scene.write_text(f"""name = "off_origin"
[sensor]
hardware = "{REPO / 'tests/fixtures/tiny_sensor.toml'}"
[mesh]
edge_mm = 3.0
contact_edge_mm = 1.5
refine_margin_mm = 1.0
[[indenters]]
name = "cad"
mesh = "cad_part.stl"
units = "mm"
{anchor_line}start_xy_mm = [{start_xy[0]}, {start_xy[1]}]
start_gap_mm = 0.2
trajectory = [{{ kind = "press", depth_mm = {depth_mm}, frames = 1 }}]
""")
    return scene


def _body_centre(setup) -> np.ndarray:
    ind = setup.indenters[0]
    return ind.start_pose[:3, :3] @ BODY_OFFSET_MM + ind.start_pose[:3, 3]


def test_footprint_anchor_puts_the_body_over_start_xy(tmp_path: Path):
    default = load_setup(_scene(tmp_path, None))
    assert default.scene.indenters[0].anchor == "footprint"
    assert np.allclose(_body_centre(default)[:2], [1.0, 2.0], atol=1e-6)
    assert abs(_body_centre(default)[2] - RADIUS_MM - (5.0 + 0.2)) < 1e-6  # lowest point start_gap above the gel
    by_origin = load_setup(_scene(tmp_path, "origin"))
    assert np.allclose(by_origin.indenters[0].start_pose[:2, 3], [1.0, 2.0])
    assert np.allclose(_body_centre(by_origin)[:2], [1.0, -22.0], atol=1e-6)


def test_footprint_follows_the_rotation(tmp_path: Path):
    """Turned 90 degrees about z, the body still lies over start_xy_mm (by its origin it would swing 24 mm)."""
    scene = _scene(tmp_path, None)
    scene.write_text(scene.read_text().replace("start_gap_mm = 0.2", "start_gap_mm = 0.2\nrotation_deg = [0.0, 0.0, 90.0]"))
    assert np.allclose(_body_centre(load_setup(scene))[:2], [1.0, 2.0], atol=1e-6)


def test_unknown_anchor_names_file_key_and_choices(tmp_path: Path):
    scene = _scene(tmp_path, "centre")
    with pytest.raises(ConfigError) as e:
        load_setup(scene)
    msg = str(e.value)
    assert str(scene) in msg and "indenters[0].anchor" in msg and "'footprint' or 'origin'" in msg


@pytest.mark.parametrize("name", sorted(LIBRARY))
def test_library_indenters_are_placed_as_before(name: str):
    """The shipped indenters are centred: for them, turned about z (what scenes and [randomize] do), the
    footprint anchor gives exactly the pose of the origin anchor, i.e. the placement before anchors existed."""
    mesh = load_indenter_mesh(REPO / "scenes" / "indenters" / f"{name}.stl", "mm")
    for angle in (0.0, 37.0, 90.0, 143.5, 180.0):
        for xy in ((0.0, 0.0), (-6.0, 3.5), (5.25, -4.0)):
            cfg = {"name": "i", "mesh": "x.stl", "units": "mm", "start_xy_mm": xy, "rotation_deg": (0.0, 0.0, angle),
                   "trajectory": [{"kind": "hold", "frames": 1}]}
            poses = [start_pose(Indenter(**cfg, anchor=a), mesh, (32.0, 24.0, 5.0), source="s", key="k")
                     for a in ("footprint", "origin")]
            assert np.array_equal(poses[0], poses[1]), (name, angle, xy)


def _pressed(setup, depth_mm: float) -> np.ndarray:
    """The start pose lowered until the lowest point is ``depth_mm`` below the undeformed surface."""
    pose = setup.indenters[0].start_pose.copy()
    pose[2, 3] -= 0.2 + depth_mm
    return pose


def test_a_press_beside_the_gel_is_refused(tmp_path: Path):
    setup = load_setup(_scene(tmp_path, "origin"))  # the body lies at y = -22 mm, the gel spans y -12..12 mm
    with pytest.raises(SimulationFailed) as e:
        check_pressed_indenters_touch(setup, 3, [_pressed(setup, 0.5)], [np.zeros(3)], [0.5])
    msg = str(e.value)
    assert msg.startswith("frame 3: indenter 'cad' is pressed 0.5 mm") and "beside the gel's top face" in msg
    assert "anchor = 'origin'" in msg
    # not pressed in (within PRESSED_MM), or pressed with a force: nothing to say
    check_pressed_indenters_touch(setup, 3, [_pressed(setup, PRESSED_MM)], [np.zeros(3)], [PRESSED_MM])
    check_pressed_indenters_touch(setup, 3, [_pressed(setup, 0.5)], [np.array([0.0, 0.0, -0.1])], [0.5])


def test_a_press_over_the_gel_without_force_is_refused(tmp_path: Path):
    setup = load_setup(_scene(tmp_path, None))
    with pytest.raises(SimulationFailed, match="frame 0: indenter 'cad' .* over the gel, .*contact_edge_mm"):
        check_pressed_indenters_touch(setup, 0, [_pressed(setup, 0.3)], [np.zeros(3)], [0.3])


@pytest.mark.slow
def test_off_origin_cad_part_presses_the_gel_and_by_its_origin_is_refused(tmp_path: Path):
    """End to end (meshing and one FEM frame each, about a minute on 2 cores): the issue's case."""
    runner = CliRunner()
    r = runner.invoke(app, ["simulate", str(_scene(tmp_path, "origin", (0.0, 0.0))), "--out", str(tmp_path / "o")])
    assert r.exit_code == 1, r.output
    failure = json.loads((tmp_path / "o" / "summary.json").read_text())["failure"]
    assert failure["frame"] == 0 and "indenter 'cad' is pressed 0.5 mm" in failure["message"]
    assert "beside the gel's top face" in failure["message"]
    assert not (tmp_path / "o" / "frames" / "000000.json").exists()

    r = runner.invoke(app, ["simulate", str(_scene(tmp_path, None, (0.0, 0.0))), "--out", str(tmp_path / "f")])
    assert r.exit_code == 0, r.output
    record = json.loads((tmp_path / "f" / "frames" / "000000.json").read_text())
    assert record["indenters"][0]["depth_mm"] == pytest.approx(0.5)
    assert -record["indenters"][0]["force_n"][2] > 0.01  # it pressed the gel
