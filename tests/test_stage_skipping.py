"""Stages run only when an output needs them."""

from __future__ import annotations

import dataclasses
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import REPO

from transtac_sim.dataset.sequence import StageClock
from transtac_sim.scene_setup import load_setup
from transtac_sim.simulation import simulate_frames


def test_contact_free_scene_never_calls_the_fem_solver(monkeypatch):
    monkeypatch.setitem(sys.modules, "transtac_sim.physics", None)  # any import of it now fails
    monkeypatch.setitem(sys.modules, "warp", None)
    setup = load_setup(REPO / "scenes" / "rest_uv_only.toml")
    clock = StageClock()
    frames = list(simulate_frames(setup, 3, clock))
    assert [f.frame for f in frames] == [0, 1, 2]
    for f in frames:
        assert np.array_equal(f.markers_gel_mm, setup.sensor.markers_rest_gel_mm)
        assert f.solver == {"converged": True, "iterations": 0, "residual": 0.0, "seconds": 0.0}
    assert "physics" not in clock.seconds and "mesh" not in clock.seconds


def test_uv_only_scene_never_builds_the_white_light_scene(tmp_path):
    from transtac_sim.dataset.randomize import Variant
    from transtac_sim.dataset.render_stage import FrameRenderer

    setup = load_setup(REPO / "tests" / "fixtures" / "tiny_rest.toml")
    scene = setup.scene.model_copy(update={"outputs": setup.scene.outputs.model_copy(
        update={"illuminations": ["uv"], "cameras": ["left"]})})
    setup = dataclasses.replace(setup, scene=scene)
    fr = FrameRenderer(setup, Variant(scene), StageClock())
    assert list(fr.renderer.assemblies) == ["uv"] and list(fr.renderer.cameras) == ["left"]
    phys = next(simulate_frames(setup, 1, StageClock()))
    images, depth, views = fr.render(phys, seed=0)
    assert list(images) == [("left", "uv")] and depth == {} and list(views) == ["left"]


def test_failed_frame_is_recorded_with_its_reason_and_not_written(tmp_path, monkeypatch):
    import json

    import transtac_sim.simulation as simulation
    from transtac_sim.dataset.generate import generate

    real = simulation.simulate_frames

    def failing(setup, frames, clock):
        for f in real(setup, frames, clock):
            if f.frame == 1:
                raise simulation.SimulationFailed(1, "Newton did not converge (test)")
            yield f

    monkeypatch.setattr(simulation, "simulate_frames", failing)
    report = generate(REPO / "tests" / "fixtures" / "tiny_rest.toml", tmp_path / "ds", frames=3, sequences=1)
    samples = json.loads((tmp_path / "ds" / "manifest.json").read_text())["samples"]
    assert [s["status"] for s in samples] == ["done", "failed", "failed"]
    assert "Newton did not converge (test)" in samples[1]["reason"] and "frame 1 of this sequence failed" in samples[2]["reason"]
    assert report.frames_done == 1 and len(report.frames_failed) == 2
    assert not (tmp_path / "ds" / "sequences" / "seq_00000" / "000001").exists()

    # resumed: the recorded failure is kept and the sequence is not solved again, unless asked to retry
    calls = []

    def counting(setup, frames, clock):
        calls.append(frames)
        yield from real(setup, frames, clock)

    monkeypatch.setattr(simulation, "simulate_frames", counting)
    again = generate(REPO / "tests" / "fixtures" / "tiny_rest.toml", tmp_path / "ds", frames=3, sequences=1)
    assert not calls and again.frames_done == 1 and again.frames_failed == report.frames_failed
    retried = generate(REPO / "tests" / "fixtures" / "tiny_rest.toml", tmp_path / "ds", frames=3, sequences=1,
                       retry_failed=True)
    assert calls == [3] and retried.frames_done == 3 and not retried.frames_failed
    assert not (tmp_path / "ds" / ".resume" / "seq_00000.json").exists()


def test_render_command_writes_images_labels_and_contact_sheet(tmp_path):
    from typer.testing import CliRunner

    from transtac_sim.cli import app

    r = CliRunner().invoke(app, ["render", str(REPO / "tests" / "fixtures" / "tiny_rest.toml"), "--frame", "0",
                                 "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    for name in ("left_uv.png", "right_white.png", "labels.json", "contact_sheet.png"):
        assert (tmp_path / name).is_file()


def test_an_indenter_that_only_hovers_needs_no_fem(monkeypatch, tmp_path):
    """A hold-only indenter above the gel (the fusion benchmark's scene) is rendered at its start pose,
    with zero force, and nothing imports the FEM; one that presses needs it."""
    monkeypatch.setitem(sys.modules, "transtac_sim.physics", None)
    monkeypatch.setitem(sys.modules, "warp", None)
    setup = load_setup(REPO / "scenes" / "perception" / "fusion_distances.toml")
    assert not setup.has_contact
    (f,) = list(simulate_frames(setup, 1, StageClock()))
    assert np.array_equal(f.indenter_poses[0], setup.indenters[0].start_pose)
    assert np.array_equal(f.forces_n[0], np.zeros(3)) and f.depths_mm == [0.0]
    pressed = dataclasses.replace(setup, indenters=[dataclasses.replace(
        setup.indenters[0], config=setup.indenters[0].config.model_copy(update={"start_gap_mm": 0.0}))])
    assert pressed.has_contact


def test_a_scene_solves_with_its_physics_settings(monkeypatch):
    """simulation.py hands the scene's [physics] to the solver: Newton's force test at the scenes' default 3e-3 where
    a scene leaves it unset (tiny_press), off at 0, train_random's 1e-3."""
    import transtac_sim.meshing
    import transtac_sim.physics

    class Stop(Exception):
        pass

    def solver_settings(setup):
        seen = []

        def capture(*args, settings, **kwargs):
            seen.append(settings)
            raise Stop

        monkeypatch.setattr(transtac_sim.physics, "QuasiStaticSolver", capture)
        meshed = SimpleNamespace(mesh=SimpleNamespace(vertices_mm=np.zeros((4, 3)), tets=np.array([[0, 1, 2, 3]])))
        monkeypatch.setattr(transtac_sim.meshing, "mesh_gel", lambda s: meshed)
        with pytest.raises(Stop):
            next(simulate_frames(setup, 1, StageClock()))
        (settings,) = seen
        return settings

    tiny = load_setup(REPO / "tests" / "fixtures" / "tiny_press.toml")
    assert solver_settings(tiny).newton_force_rtol == 3e-3
    physics = tiny.scene.physics.model_copy(update={"newton_force_rtol": 0.0, "friction_lag_moves": 2})
    off = solver_settings(dataclasses.replace(tiny, scene=tiny.scene.model_copy(update={"physics": physics})))
    assert off.newton_force_rtol is None and off.friction_lag_moves == 2
    assert solver_settings(load_setup(REPO / "scenes" / "train_random.toml")).newton_force_rtol == 1e-3
