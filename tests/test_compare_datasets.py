"""scripts/compare_datasets.py: frame-by-frame label differences of two runs, against hand-computed values."""

import json
import sys
from pathlib import Path

import pytest
import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import compare_datasets as cmp  # noqa: E402


def _marker(mid: int, xyz: list[float], uv_left: list[float], visible_right: bool = True) -> dict:
    return {"id": mid, "xyz_rest_mm": [0.0, 0.0, 0.0], "xyz_mm": xyz,
            "left": {"uv": uv_left, "visible": True}, "right": {"uv": [10.0, 10.0], "visible": visible_right}}


def _write(root: Path, seq: str, frame: str, markers: list[dict], force: list[float], iterations: int) -> None:
    d = root / "sequences" / seq / frame
    d.mkdir(parents=True)
    (d / "labels.json").write_text(json.dumps({
        "sequence": seq, "frame": int(frame.split("_")[1]), "markers": markers,
        "indenters": [{"name": "object", "force_n": force}],
        "solver": {"iterations": iterations, "seconds": iterations / 10.0}}))


def test_differences_of_two_runs(tmp_path):
    ref, run = tmp_path / "ref", tmp_path / "run"
    _write(ref, "seq_00000", "frame_0000", [_marker(0, [0, 0, 5], [1, 1]), _marker(1, [1, 0, 5], [5, 5])],
           [0.0, 0.0, -2.0], 10)
    _write(ref, "seq_00000", "frame_0001", [_marker(0, [0, 0, 5], [1, 1]), _marker(1, [1, 0, 5], [5, 5])],
           [0.0, 0.0, -1.0], 20)
    _write(ref, "seq_00001", "frame_0000", [_marker(0, [0, 0, 5], [1, 1])], [0.0, 0.0, -4.0], 4)
    # frame 0: marker 1 moved 0.03 mm and 4 px in the left image (3, 4); its right image is hidden in the run
    _write(run, "seq_00000", "frame_0000", [_marker(0, [0, 0, 5], [1, 1]),
                                            _marker(1, [1, 0.03, 5], [8, 9], visible_right=False)],
           [0.3, 0.4, -2.0], 6)
    # frame 1: the force 0.1 N off, 5 % of the sequence's largest reference force (2 N, frame 0), not of its own 1 N
    _write(run, "seq_00000", "frame_0001", [_marker(0, [0, 0, 5], [1, 1]), _marker(1, [1, 0, 5], [5, 5])],
           [0.0, 0.0, -1.1], 8)
    _write(run, "seq_00002", "frame_0000", [_marker(0, [0, 0, 5], [1, 1])], [0.0, 0.0, -4.0], 4)
    rows, only_run, only_ref = cmp.compare(run, ref)
    assert (only_run, only_ref) == (1, 1)  # seq_00002 only in the run, seq_00001 only in the reference
    assert [(r["sequence"], r["frame"]) for r in rows] == [("seq_00000", "frame_0000"), ("seq_00000", "frame_0001")]
    first, second = rows
    assert first["marker_mm"] == pytest.approx(0.03) and first["marker_px"] == pytest.approx(5.0)
    assert first["force_n"] == pytest.approx(0.5) and first["force_pct"] == pytest.approx(25.0)
    assert second["marker_mm"] == 0.0 and second["force_n"] == pytest.approx(0.1)
    assert second["force_pct"] == pytest.approx(5.0)
    assert (first["iterations"], first["iterations_ref"], second["iterations"]) == (6, 10, 8)
    text = cmp.report(rows, only_run, only_ref, run, ref, worst=1)
    assert "run 7 (7.0), reference 15 (15.0)" in text  # Newton iterations per frame, median (mean)
    assert "| largest marker distance (mm) | 0.015 / 0.027 / 0.03 |" in text
    assert text.splitlines()[-1].startswith("- seq_00000 frame_0000: markers 0.0300 mm (5.00 px)")


def test_runs_of_different_scenes_or_no_dataset_are_refused(tmp_path):
    ref, run = tmp_path / "ref", tmp_path / "run"
    _write(ref, "seq_00000", "frame_0000", [_marker(0, [0, 0, 5], [1, 1])], [0.0, 0.0, -1.0], 3)
    _write(run, "seq_00000", "frame_0000", [_marker(7, [0, 0, 5], [1, 1])], [0.0, 0.0, -1.0], 3)
    with pytest.raises(ValueError, match="marker ids differ"):
        cmp.compare(run, ref)
    with pytest.raises(typer.BadParameter, match="no sequences/ folder"):
        cmp.compare(tmp_path / "missing", ref)
