"""scripts/bench_generate.py's ``--summarize``: the lockstep estimate of batched solves against hand-counted cases, and
the summary of a dataset folder's solver records."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
from bench_generate import lockstep_ratio, solver_summary  # noqa: E402


def test_lockstep_ratio_counts_each_batch_frame_at_its_slowest_sequence():
    assert lockstep_ratio([[1, 2], [1, 2]], 2) == 1.0  # equal sequences: nothing is lost
    # frame 0 at 3 (not 1 + 3 = 4 alone), frame 1 at 4 (not 4 + 2): 2 x 7 = 14 systems against 10
    assert lockstep_ratio([[1, 4], [3, 2]], 2) == pytest.approx(14 / 10)
    # the last batch has one sequence (10 systems); a sequence that stopped after frame 0 keeps its slot (2 x (3 + 6))
    assert lockstep_ratio([[3], [2, 6], [5, 5]], 2) == pytest.approx((18 + 10) / 21)
    assert lockstep_ratio([[7, 1], [2, 9]], 1) == 1.0


def test_summary_reads_the_solver_records(tmp_path):
    for seq, its in (("seq_00000", [5, 20]), ("seq_00001", [7, 10])):
        for frame, n in enumerate(its):
            path = tmp_path / "sequences" / seq / f"{frame:06d}" / "labels.json"
            path.parent.mkdir(parents=True)
            path.write_text(json.dumps({"sequence": seq, "solver": {
                "iterations": n, "seconds": 0.5, "converged": True, "substeps": 1}}))
    text = solver_summary(tmp_path)
    assert "4 frames with labels in 2 sequences" in text
    assert "K = 2: 1.29x the Newton systems" in text  # 2 x (7 + 20) = 54 against 5 + 20 + 7 + 10 = 42
    assert "K = 4" not in text  # more than the sequences there are
    assert "seq_00001: 2 frames, 1.0 s of physics, Newton iterations [7, 10]" in text
    assert "friction's lag" not in text  # records without it (written before it was recorded)


def test_summary_gives_friction_s_lag_residual_against_the_contact_force(tmp_path):
    for frame, (lag, force) in enumerate(((0.01, [0.0, 3.0, -4.0]), (0.2, [0.0, 0.0, -2.0]), (0.5, [0.0, 0.0, 0.0]))):
        path = tmp_path / "sequences" / "seq_00000" / f"{frame:06d}" / "labels.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"sequence": "seq_00000", "frame": frame, "indenters": [{"force_n": force}], "solver": {
            "iterations": 3, "seconds": 0.5, "converged": True, "friction_lag_residual_n": lag}}))
    text = solver_summary(tmp_path, worst=1)
    # 0.01 / 5 and 0.2 / 2; the frame without contact force is left out
    assert "in 2 frames with contact: median 5.1e-02, 90th percentile 9.0e-02, max 1.0e-01" in text, text
    assert "- seq_00000 frame 1: friction's lag leaves 0.2 N against |force| 2 N (0.10); 3 Newton iterations" in text
    assert "seq_00000 frame 0: friction" not in text  # only the worst one


def test_summary_gives_the_residuals_and_where_the_largest_is(tmp_path):
    for seq, residuals in (("seq_00000", [1e-6, 33.0]), ("seq_00001", [2e-6, 3e-6])):
        for frame, r in enumerate(residuals):
            path = tmp_path / "sequences" / seq / f"{frame:06d}" / "labels.json"
            path.parent.mkdir(parents=True)
            path.write_text(json.dumps({"sequence": seq, "frame": frame, "solver": {
                "iterations": 3, "seconds": 0.5, "converged": True, "residual": r}}))
    text = solver_summary(tmp_path)
    assert "residual (labels.json solver residual, N): median 2.5e-06, max 3.30e+01 (seq_00000 frame 1)" in text, text


def test_summary_counts_the_failed_steps_by_why(tmp_path):
    """The (sub)steps that failed and were solved again in halves (labels.json ``solver.failed_steps``), counted by
    their reason without its figures, with their Newton iterations; the total of Newton iterations."""
    failed = [[{"from": 0.0, "to": 1.0, "iterations": 120, "why": "Newton iteration limit reached (its steps below "
                "newton_tol_mm at |gradient| 894 N above max_residual_n = 1 N, smallest det F 1.86e-06)"},
               {"from": 0.0, "to": 0.5, "iterations": 30, "why": "Newton made no progress: 30 steps since the lowest "
                "|gradient| of the (sub)step (2.57 N)"}],
              [], [{"from": 0.5, "to": 1.0, "iterations": 31, "why": "Newton made no progress: 30 steps since the "
                    "lowest |gradient| of the (sub)step (5.8 N)"},
                   {"from": 0.5, "to": 0.75, "iterations": 3, "why": "penetration 0.0213 mm above the tolerance"}]]
    for frame, steps in enumerate(failed):
        path = tmp_path / "sequences" / "seq_00000" / f"{frame:06d}" / "labels.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"sequence": "seq_00000", "frame": frame, "solver": {
            "iterations": 200, "seconds": 0.5, "converged": True, "substeps": 1 + len(steps), "failed_steps": steps}}))
    text = solver_summary(tmp_path)
    assert "Newton iterations per frame: median 200, max 200, 600 in all" in text, text
    assert ("failed (sub)steps, each solved again in halves: 4 in 2 frames, 184 Newton iterations; Newton iteration "
            "limit reached: 1 (120 iterations), Newton made no progress: 2 (61 iterations), penetration: 1 (3 "
            "iterations)") in text, text
