"""scripts/fem_hold_drift.py's hold bookkeeping against hand-made frames, and its refusal of a scene without a hold."""

import sys
from pathlib import Path

import numpy as np
import pytest
import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from fem_hold_drift import drift, hold_frames  # noqa: E402

from transtac_sim.scene_setup import load_setup  # noqa: E402

FIXTURES = Path(__file__).resolve().parent / "fixtures"


def test_drift_is_measured_from_the_frame_before_the_hold():
    # 4 frames of 2 markers, the last 2 held: marker 1 moves 0.3 then 0.4 mm (0.5 mm from the frame before the hold)
    markers = np.zeros((4, 2, 3))
    markers[0, :, 0] = -1.0  # a frame before the one the hold starts from: not compared
    markers[2, 1] = [0.3, 0.0, 0.0]
    markers[3, 1] = [0.3, 0.4, 0.0]
    forces = [[[3.0, 4.0, -10.0]], [[6.0, 8.0, -20.0]], [[0.6, 0.8, -19.0]], [[0.0, 0.0, -18.0]]]
    r = drift({"markers": markers.tolist(), "forces": forces, "iterations": [9, 8, 7, 6]}, held=2)
    assert r["drift_mm"] == pytest.approx([0.3, 0.5])
    assert r["tangential_n"] == pytest.approx([10.0, 1.0, 0.0])
    assert r["normal_n"] == pytest.approx([20.0, 19.0, 18.0])
    assert r["iterations"] == [8, 7, 6]


def test_hold_frames_reads_the_trajectory_and_refuses_a_scene_without_a_hold():
    assert hold_frames(load_setup(FIXTURES / "tiny_slide_hold.toml")) == 4
    with pytest.raises(typer.BadParameter, match="does not end its trajectory with a hold"):
        hold_frames(load_setup(FIXTURES / "tiny_press_slide.toml"))
