"""``generate --mps``: the MPS control daemon started and stopped around the workers (gpu_sharing.py), checked with a
stand-in ``nvidia-cuda-mps-control`` that records how it was called, and the clear errors where MPS cannot run."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from mps_stand_in import stand_in

from transtac_sim.dataset.generate import generate
from transtac_sim.gpu_sharing import MpsUnavailable, mps_server

REPO = Path(__file__).resolve().parents[1]


def test_starts_the_daemon_and_stops_it(tmp_path: Path, monkeypatch):
    log = tmp_path / "calls.log"
    stand_in(tmp_path / "bin", log)
    monkeypatch.setenv("PATH", f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}")
    with mps_server() as ours:
        assert ours
        assert log.read_text().splitlines() == ["start"]
    assert log.read_text().splitlines() == ["start", "command quit"]


def test_a_running_daemon_is_used_and_left_running(tmp_path: Path, monkeypatch):
    log = tmp_path / "calls.log"
    stand_in(tmp_path / "bin", log, "An instance of this daemon is already running", 1)
    monkeypatch.setenv("PATH", f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}")
    with mps_server() as ours:
        assert not ours
    assert log.read_text().splitlines() == ["start"]


def test_a_daemon_that_fails_to_start_is_an_error(tmp_path: Path, monkeypatch):
    stand_in(tmp_path / "bin", tmp_path / "calls.log", "cannot create the pipe directory", 1)
    monkeypatch.setenv("PATH", f"{tmp_path / 'bin'}{os.pathsep}{os.environ['PATH']}")
    with pytest.raises(MpsUnavailable, match="cannot create the pipe directory"):
        with mps_server():
            pass


def test_generate_without_mps_here_writes_nothing(tmp_path: Path, monkeypatch):
    empty = tmp_path / "bin"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    out = tmp_path / "ds"
    with pytest.raises(MpsUnavailable, match="not on PATH"):
        generate(REPO / "scenes" / "quickstart.toml", out, frames=1, workers=2, mps=True)
    assert not out.exists()
    with pytest.raises(MpsUnavailable, match="without --address"):
        generate(REPO / "scenes" / "quickstart.toml", out, frames=1, executor="ray", address="auto", mps=True)
    assert not out.exists()
