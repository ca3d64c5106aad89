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
    assert study.Setting(0.65, 1, 2).label() == "0.65/1/2" and study.Setting(0.8, 4).label() == "0.8/4"
    for bad in ("0.8", "0.8/4/2/1", "a/4", "0/4", "0.8/0", "0.8/4/0"):
        with pytest.raises(typer.BadParameter):
            study.parse_setting(bad)


def test_p2_unknowns_count_vertices_and_edges():
    assert study.p2_unknowns(np.array([[0, 1, 2, 3]])) == 3 * (4 + 6)
    assert study.p2_unknowns(np.array([[0, 1, 2, 3], [1, 2, 3, 4]])) == 3 * (5 + 9)  # a shared face: 3 edges shared


def test_errors_against_the_reference():
    rest = np.zeros((2, 3))
    ref = {"markers": [[[0, 0, 0], [0, 0, 0]], [[0, 0, -1.0], [0, 0, 0]]], "forces": [[0, 0, -1.0], [0, 0, -2.0]]}
    row = {"markers": [[[0, 0, 0], [0, 0, 0]], [[0, 0, -1.0], [0.03, 0.04, 0]]], "forces": [[0, 0, -1.0], [0.2, 0, -2.0]]}
    e = study.errors(row, ref, rest)
    assert e["marker_max_mm"] == pytest.approx(0.05) and e["marker_max_per_frame_mm"] == pytest.approx([0.0, 0.05])
    assert e["marker_rms_mm"] == pytest.approx(np.sqrt(0.05 ** 2 / 4))  # one of four marker-frames is off
    assert e["largest_displacement_mm"] == pytest.approx(1.0) and e["marker_max_pct"] == pytest.approx(5.0)
    assert e["force_max_pct"] == pytest.approx(10.0)  # 0.2 N off at a largest reference force of 2 N


def test_split_frames_keep_every_split_th_and_sum_its_cost(monkeypatch):
    setup = load_setup(FIXTURE)
    solved_frames = []

    def fake_frames(split_setup, frames, clock):
        solved_frames.append((frames, [seg.frames for seg in split_setup.indenters[0].config.trajectory]))
        for f in range(frames):
            yield SimpleNamespace(frame=f, markers_gel_mm=np.full((1, 3), float(f)), forces_n=[np.array([0, 0, -f])],
                                  solver={"seconds": 1.0, "iterations": f, "substeps": 1})

    monkeypatch.setattr(study, "simulate_frames", fake_frames)
    monkeypatch.setattr(study, "mesh_gel", lambda s: SimpleNamespace(mesh=SimpleNamespace(tets=np.array([[0, 1, 2, 3]]))))
    r = study.solve(setup, 3, split=2)
    original = [seg.frames for seg in setup.indenters[0].config.trajectory]
    assert solved_frames == [(6, [2 * n for n in original])]  # every segment's frames doubled, 6 frames solved
    assert [m[0][0] for m in r["markers"]] == [1.0, 3.0, 5.0]  # frame f is the split scene's frame 2 (f + 1) - 1
    assert r["seconds"] == [2.0, 2.0, 2.0] and r["iterations"] == [0 + 1, 2 + 3, 4 + 5] and r["substeps"] == [2, 2, 2]
