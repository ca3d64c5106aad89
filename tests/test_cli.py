"""The command line as a user runs it."""

from __future__ import annotations

import json

from conftest import REPO, edit
from typer.testing import CliRunner

from transtac_sim.cli import app

runner = CliRunner()


def test_mesh_writes_mesh_markers_summary_and_picture(tmp_path):
    out = tmp_path / "mesh"
    r = runner.invoke(app, ["mesh", str(REPO / "scenes/press_slide.toml"), "--out", str(out)])
    assert r.exit_code == 0, r.output
    assert "tets" in r.output and "min dihedral" in r.output and "s total" in r.output
    summary = json.loads((out / "summary.json").read_text())
    markers = json.loads((out / "markers.json").read_text())["markers"]
    assert summary["markers"] == len(markers) == 110 and summary["quality"]["tets"] > 1000
    assert (out / "layout.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert (out / "gel_mesh.npz").stat().st_size > 0


def test_info_and_bad_config_exit_code(repo_copy):
    r = runner.invoke(app, ["info", str(REPO / "scenes/press_slide.toml")])
    assert r.exit_code == 0 and "110 x r = 0.25 mm" in r.output
    bad = edit(repo_copy / "scenes/press_slide.toml", "friction = 0.5", "friction = -1")
    r = runner.invoke(app, ["info", str(bad)])
    assert r.exit_code == 2 and "indenters[0].friction" in r.output


def test_generate_mps_without_nvidia_driver_is_a_clear_error(tmp_path, monkeypatch):
    """`generate --mps` on a machine without NVIDIA's MPS control program: exit 2, what is missing, nothing written."""
    empty = tmp_path / "bin"
    empty.mkdir()
    monkeypatch.setenv("PATH", str(empty))
    out = tmp_path / "ds"
    r = runner.invoke(app, ["generate", str(REPO / "scenes/quickstart.toml"), "--out", str(out), "--frames", "1",
                            "--workers", "2", "--mps"])
    assert r.exit_code == 2, r.output
    assert "nvidia-cuda-mps-control is not on PATH" in " ".join(r.output.split())
    assert not out.exists()


def test_ctrl_c_inside_a_library_is_told_from_its_errors():
    """Ctrl-C during a Mitsuba render comes back as Mitsuba's RuntimeError caused by the KeyboardInterrupt:
    generate then says the run can be resumed instead of printing a traceback; other errors still propagate."""
    from transtac_sim.cli import _interrupted

    try:
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise RuntimeError("drjit.custom(...): error while performing a custom operation") from e
    except RuntimeError as e:
        assert _interrupted(e)
    assert not _interrupted(RuntimeError("the lens distortion is not invertible"))
    assert _interrupted(KeyboardInterrupt())
