"""scripts/compare_datasets.py: frame-by-frame label differences of two runs, against hand-computed values."""

import json
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import compare_datasets as cmp  # noqa: E402

from transtac_sim.dataset import contract  # noqa: E402


def _marker(mid: int, xyz: list[float], uv_left: list[float], right: tuple | None = ([10.0, 10.0], True)) -> dict:
    m = {"id": mid, "xyz_rest_mm": [0.0, 0.0, 0.0], "xyz_mm": xyz, "left": {"uv": uv_left, "visible": True}}
    if right is not None:
        m["right"] = {"uv": right[0], "visible": right[1]}
    return m


def _write(root: Path, seq: int, frame: int, markers: list[dict], forces: list[list[float]], iterations: int) -> None:
    d = contract.frame_dir(root, contract.sequence_name(seq), frame)
    d.mkdir(parents=True)
    (d / "labels.json").write_text(json.dumps({
        "sequence": contract.sequence_name(seq), "frame": frame, "markers": markers,
        "indenters": [{"name": f"object{i}", "force_n": f} for i, f in enumerate(forces)],
        "solver": {"iterations": iterations, "seconds": iterations / 10.0}}))


def test_differences_of_two_runs(tmp_path):
    ref, run = tmp_path / "ref", tmp_path / "run"
    two = [_marker(0, [0, 0, 5], [1, 1]), _marker(1, [1, 0, 5], [5, 5])]
    _write(ref, 0, 0, two, [[0.0, 0.0, -2.0]], 10)
    _write(ref, 0, 1, two, [[0.0, 0.0, -1.0]], 20)
    _write(ref, 1, 0, two[:1], [[0.0, 0.0, -4.0]], 4)
    # frame 0: the force 0.1 N off, 5 % of the sequence's largest reference force (2 N, frame 0)
    _write(run, 0, 0, two, [[0.0, 0.0, -2.1]], 6)
    # frame 1: marker 1 moved 0.03 mm and 5 px in the left image (3, 4); in the right image it is hidden in the run,
    # 50 px away, which is not a distance; the force 0.5 N off, 25 % of the sequence's 2 N (not of the frame's 1 N)
    _write(run, 0, 1, [_marker(0, [0, 0, 5], [1, 1]), _marker(1, [1, 0.03, 5], [8, 9], ([60.0, 10.0], False))],
           [[0.3, 0.4, -1.0]], 8)
    _write(run, 2, 0, two[:1], [[0.0, 0.0, -4.0]], 4)
    rows, only_run, only_ref = cmp.compare(run, ref)
    assert (only_run, only_ref) == (1, 1)  # seq_00002 only in the run, seq_00001 only in the reference
    assert [(r["sequence"], r["frame"]) for r in rows] == [("seq_00000", "000000"), ("seq_00000", "000001")]
    first, second = rows
    assert first["marker_mm"] == 0.0 and first["marker_px"] == 0.0 and first["visibility_flips"] == 0
    assert first["force_n"] == pytest.approx(0.1) and first["force_pct"] == pytest.approx(5.0)
    assert second["marker_mm"] == pytest.approx(0.03) and second["marker_px"] == pytest.approx(5.0)
    assert second["visibility_flips"] == 1
    assert second["force_n"] == pytest.approx(0.5) and second["force_pct"] == pytest.approx(25.0)
    assert (first["iterations"], first["iterations_ref"], second["iterations"]) == (6, 10, 8)
    text = cmp.report(rows, only_run, only_ref, run, ref, worst=1)
    assert "run 7 (7.0), reference 15 (15.0)" in text  # Newton iterations per frame, median (mean)
    assert "| largest marker distance (mm) | 0.015 / 0.027 / 0.03 (2) |" in text
    assert "Markers visible in one run only: 1 (marker, camera) pairs in all." in text
    # the worst frame, not the first
    assert text.splitlines()[-1].startswith("- seq_00000 000001: markers 0.0300 mm (5.00 px)")
    out = tmp_path / "report.md"
    result = CliRunner().invoke(_app(), [str(run), str(ref), "--worst", "1", "--md-out", str(out)])
    assert result.exit_code == 0 and out.read_text() == text + "\n"


def _app() -> typer.Typer:
    app = typer.Typer(add_completion=False)
    app.command()(cmp.main)
    return app


def test_what_a_frame_lacks_is_no_difference_and_one_camera_is_enough(tmp_path):
    """A scene without indenters has no force difference; a sequence whose reference force is 0 has no percentage; a
    frame with no marker visible in both runs no image distance; a one-camera dataset compares that camera."""
    ref, run = tmp_path / "ref", tmp_path / "run"
    _write(ref, 0, 0, [_marker(0, [0, 0, 5], [1, 1], right=None)], [], 1)
    _write(run, 0, 0, [_marker(0, [0, 0, 5.01], [1, 2], right=None)], [], 1)
    _write(ref, 1, 0, [_marker(0, [0, 0, 5], [1, 1], ([3.0, 3.0], False))], [[0.0, 0.0, 0.0]], 1)
    _write(run, 1, 0, [_marker(0, [0, 0, 5], [1, 1], ([3.0, 3.0], False))], [[0.0, 0.0, -0.2]], 1)
    rows, _, _ = cmp.compare(run, ref)
    assert rows[0]["marker_px"] == pytest.approx(1.0) and np.isnan(rows[0]["force_n"])
    assert rows[0]["marker_mm"] == pytest.approx(0.01)
    assert rows[1]["force_n"] == pytest.approx(0.2) and np.isnan(rows[1]["force_pct"])
    text = cmp.report(rows, 0, 0, run, ref, worst=0)
    assert "| the same, % of the sequence's largest reference force | none |" in text
    assert "| largest indenter force difference (N) | 0.2 / 0.2 / 0.2 (1) |" in text


def test_runs_of_different_scenes_or_no_dataset_are_refused(tmp_path):
    ref, run, other = tmp_path / "ref", tmp_path / "run", tmp_path / "other"
    _write(ref, 0, 0, [_marker(0, [0, 0, 5], [1, 1])], [[0.0, 0.0, -1.0]], 3)
    _write(run, 0, 0, [_marker(7, [0, 0, 5], [1, 1])], [[0.0, 0.0, -1.0]], 3)
    _write(other, 0, 0, [_marker(0, [0, 0, 5], [1, 1])], [[0.0, 0.0, -1.0], [0.0, 0.0, 0.0]], 3)
    with pytest.raises(ValueError, match=r"markers \(id\) differ"):
        cmp.compare(run, ref)
    with pytest.raises(ValueError, match=r"indenters \(name\) differ"):
        cmp.compare(other, ref)
    with pytest.raises(typer.BadParameter, match="no sequences/ folder"):
        cmp.compare(tmp_path / "missing", ref)
