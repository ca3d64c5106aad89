"""Stages run only when an output needs them."""

from __future__ import annotations

import sys

import numpy as np
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
