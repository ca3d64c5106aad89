"""scripts/fem_slide_error_vs_runtime.py: its settings, unknown count, errors and split-frame bookkeeping, against
hand-counted cases (the solves themselves are the FEM tests' business)."""

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import fem_slide_error_vs_runtime as study  # noqa: E402

from transtac_sim.scene_setup import load_setup  # noqa: E402

FIXTURE = Path(__file__).resolve().parent / "fixtures" / "tiny_press_slide.toml"


def test_settings_parse_and_refuse_what_they_cannot_be():
    assert study.parse_setting("0.8/4") == study.Setting(0.8, 4, 1)
    assert study.parse_setting(" 0.65/1/2 ") == study.Setting(0.65, 1, 2)
    assert study.parse_setting("0.8/4/1/1e-3") == study.Setting(0.8, 4, 1, 1e-3)
    assert study.parse_setting("0.8/4/1/0") == study.Setting(0.8, 4, 1, 0.0)
    assert study.Setting(0.65, 1, 2).label() == "0.65/1/2" and study.Setting(0.8, 4).label() == "0.8/4"
    assert study.Setting(0.8, 4, 1, 3e-3).label() == "0.8/4/1/0.003"
    assert study.Setting(0.8, 4, 1, 0.0).label() == "0.8/4/1/0"
    assert study.parse_setting("0.8/1/1/-/0.2") == study.Setting(0.8, 1, 1, None, 0.2)  # the scene's force test
    assert study.parse_setting("0.8/1/1/0/0.2") == study.Setting(0.8, 1, 1, 0.0, 0.2)
    assert study.Setting(0.8, 1, 1, None, 0.2).label() == "0.8/1/1/-/0.2"
    for setting in (study.Setting(0.8, 4), study.Setting(0.65, 1, 2), study.Setting(0.8, 4, 1, 1e-3),
                    study.Setting(0.8, 1, 1, None, 0.2), study.Setting(0.8, 1, 2, 0.0, 0.1)):
        assert study.parse_setting(setting.label()) == setting
    with pytest.raises(typer.BadParameter, match="SLIP must be within"):
        study.parse_setting("0.8/4/1/1e-3/2")
    for bad in ("0.8", "0.8/4/2/1", "0.8/4/2/-1e-3", "0.8/4/1/-/0", "0.8/4/1/-/0.1/1", "a/4", "0/4", "0.8/0",
                "0.8/4/0"):
        with pytest.raises(typer.BadParameter):
            study.parse_setting(bad)


def test_a_setting_sets_the_force_test_or_leaves_the_scenes():
    """RTOL replaces the scene's [physics] newton_force_rtol (0: off); without it the scene's stands (3e-3 by default,
    config/scene.py), and the row records what was solved with."""
    setup = load_setup(FIXTURE)
    assert setup.scene.physics.newton_force_rtol == 3e-3
    for setting, rtol in ((study.Setting(1.5, 4), 3e-3), (study.Setting(1.5, 4, 1, 1e-3), 1e-3),
                          (study.Setting(1.5, 4, 1, 0.0), 0.0)):
        solved = study.with_setting(setup, setting, "cpu")
        assert solved.scene.physics.newton_force_rtol == rtol
        assert study.solved_with(solved) == {"force_rtol": rtol, "slip_mm": 0.05}
    assert study.rtol_cell({"force_rtol": 0.0}) == "off" and study.rtol_cell({}) == "off"
    assert study.rtol_cell({"force_rtol": 3e-3}) == "0.003"


def test_a_setting_sets_the_smoothing_over_the_runs_or_leaves_the_scenes():
    """SLIP replaces [physics] friction_slip_mm; without it --friction-slip-mm's (``slip_mm``) stands, else the
    scene's (0.05 mm by default, config/scene.py)."""
    setup = load_setup(FIXTURE)
    assert setup.scene.physics.friction_slip_mm == 0.05
    for setting, run_slip, slip in ((study.Setting(1.5, 4), None, 0.05), (study.Setting(1.5, 4), 0.02, 0.02),
                                    (study.Setting(1.5, 4, 1, None, 0.2), None, 0.2),
                                    (study.Setting(1.5, 4, 1, None, 0.2), 0.02, 0.2)):
        assert study.with_setting(setup, setting, "cpu", slip_mm=run_slip).scene.physics.friction_slip_mm == slip
    assert study.slip_cell({"slip_mm": 0.2}) == "0.2" and study.slip_cell({}) == "-"


def test_p2_unknowns_count_vertices_and_edges():
    assert study.p2_unknowns(np.array([[0, 1, 2, 3]])) == 3 * (4 + 6)
    assert study.p2_unknowns(np.array([[0, 1, 2, 3], [1, 2, 3, 4]])) == 3 * (5 + 9)  # a shared face: 3 edges shared


def test_errors_against_the_reference():
    rest = np.zeros((2, 3))
    # two frames, two markers, two indenters: forces (frames, indenters, 3)
    ref = {"markers": [[[0, 0, 0], [0, 0, 0]], [[0, 0, -1.0], [0, 0, 0]]],
           "forces": [[[0, 0, -1.0], [0, 0, 0]], [[0, 0, -2.0], [0, 0, -0.5]]]}
    row = {"markers": [[[0, 0, 0], [0, 0, 0]], [[0, 0, -1.0], [0.03, 0.04, 0]]],
           "forces": [[[0, 0, -1.0], [0, 0, 0]], [[0.2, 0, -2.0], [-0.2, 0, -0.5]]]}
    e = study.errors(row, ref, rest)
    assert e["marker_max_mm"] == pytest.approx(0.05) and e["marker_max_per_frame_mm"] == pytest.approx([0.0, 0.05])
    assert e["marker_rms_mm"] == pytest.approx(np.sqrt(0.05 ** 2 / 4))  # one of four marker-frames is off
    assert e["largest_displacement_mm"] == pytest.approx(1.0) and e["marker_max_pct"] == pytest.approx(5.0)
    # 0.2 N off on each indenter (opposite: a sum over indenters would see none) at a largest reference force of 2 N
    assert e["force_max_pct"] == pytest.approx(10.0)


def test_split_frames_keep_every_split_th_and_sum_its_cost(monkeypatch):
    setup = load_setup(FIXTURE)
    solved_frames = []

    meshed = SimpleNamespace(mesh=SimpleNamespace(tets=np.array([[0, 1, 2, 3]])))

    def fake_frames(split_setup, frames, clock):
        # mesh_gel imported as simulation.py imports it: the unsplit scene's mesh, not a new one
        from transtac_sim.meshing import mesh_gel

        assert mesh_gel(split_setup) is meshed
        solved_frames.append((frames, [seg.frames for seg in split_setup.indenters[0].config.trajectory]))
        for f in range(frames):
            yield SimpleNamespace(frame=f, markers_gel_mm=np.full((1, 3), float(f)), forces_n=[np.array([0, 0, -f])],
                                  solver={"seconds": 1.0, "iterations": f, "substeps": 1})

    monkeypatch.setattr(study, "simulate_frames", fake_frames)
    monkeypatch.setattr(study, "mesh_gel", lambda s: meshed)
    r = study.solve(setup, 3, split=2)
    original = [seg.frames for seg in setup.indenters[0].config.trajectory]
    assert solved_frames == [(6, [2 * n for n in original])]  # every segment's frames doubled, 6 frames solved
    assert [m[0][0] for m in r["markers"]] == [1.0, 3.0, 5.0]  # frame f is the split scene's frame 2 (f + 1) - 1
    assert r["seconds"] == [2.0, 2.0, 2.0] and r["iterations"] == [0 + 1, 2 + 3, 4 + 5] and r["substeps"] == [2, 2, 2]


def test_a_failed_setting_gets_its_row_and_the_others_go_on(monkeypatch):
    def fake_solve(setup, frames, split=1):
        if setup.scene.mesh.contact_edge_mm == 2.0:
            raise study.SimulationFailed(1, "did not converge")
        shift = 0.01 if setup.scene.mesh.contact_edge_mm == 1.8 else 0.0
        markers = [[[0.0, 0.0, -0.5 * (f + 1) + shift]] for f in range(frames)]
        return {"markers": markers, "forces": [[[0.0, 0.0, -1.0]]] * frames, "seconds": [1.0] * frames,
                "iterations": [3] * frames, "substeps": [split] * frames, "tets": 10, "dofs": 30}

    monkeypatch.setattr(study, "solve", fake_solve)
    settings = [study.Setting(2.0, 4), study.Setting(1.8, 4, 2, 0.0, 0.2)]
    data = study.measure(FIXTURE, load_setup(FIXTURE), 2, settings, study.Setting(1.5, 4), "cpu", False, None, None)
    failed, solved = data["rows"]
    assert failed["failed"] == "frame 1: did not converge" and "marker_max_mm" not in failed
    assert solved["marker_max_mm"] == pytest.approx(0.01) and solved["split"] == 2
    assert failed["force_rtol"] == 3e-3 and solved["force_rtol"] == 0.0  # the scene's, and the setting's (off)
    assert failed["slip_mm"] == 0.05 and solved["slip_mm"] == 0.2
    text = study.report(data, "fem_slide_error_vs_runtime")
    rows = [line for line in text.splitlines() if line.startswith("| ") and "contact edge" not in line]
    assert [line.count("|") for line in rows] == [15, 15, 15]  # 14 cells each: the failed row too
    assert "failed: frame 1: did not converge" in rows[0] and rows[2].startswith("| 1.5 (reference)")
    assert [line.split("|")[4].strip() for line in rows] == ["0.003", "off", "0.003"]
    assert [line.split("|")[5].strip() for line in rows] == ["0.05", "0.2", "0.05"]
