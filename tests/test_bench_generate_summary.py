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
