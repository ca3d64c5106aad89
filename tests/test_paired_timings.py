"""scripts/paired_timings.py: the paired comparison of two trees' profile runs, against ratios known by construction,
and one alternated run of the tiny fixture."""

import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
import paired_timings  # noqa: E402


def _write_runs(out: Path, before: list[float], after: list[float]) -> None:
    for k, (b, a) in enumerate(zip(before, after, strict=True), start=1):
        for tree, seconds in (("b", b), ("a", a)):
            summary = f"9 frame(s), {seconds:.2f} s, {120 + k} Newton iterations (7.4 ms per iteration)"
            (out / f"{tree}{k}.txt").write_text(f"frame 1: ...\nscenes/x.toml on cuda:0, ...: {summary}\n")


def test_the_summary_reads_each_pair_and_bounds_the_median_ratio(tmp_path):
    before = [1.00, 1.10, 0.90, 1.20, 1.00, 0.95, 1.05]
    after = [0.90 * b for b in before]  # every pair 0.9 whatever the machine's drift
    _write_runs(tmp_path, before, after)
    summary = paired_timings.read_pairs(tmp_path)
    assert summary.before_s == before and summary.after_s == pytest.approx([round(a, 2) for a in after])
    assert summary.before_iterations == list(range(121, 128))
    assert summary.ratio_median == pytest.approx(0.9, abs=0.01)
    low, high = summary.ratio_interval
    assert low <= summary.ratio_median <= high < 1.0
    assert not any("holds 1" in line for line in summary.lines())


def test_pairs_that_straddle_one_are_not_told_apart():
    ratios = np.array([0.9, 1.1, 0.95, 1.05, 1.0, 0.92, 1.08])
    summary = paired_timings.summarize_pairs([(1.0, 100)] * len(ratios), [(r, 100) for r in ratios])
    low, high = summary.ratio_interval
    assert low < 1.0 < high and summary.ratio_median == pytest.approx(1.0)
    assert "holds 1" in summary.lines()[-1]
    # the interval is the bootstrap's: narrower for the same spread with more pairs
    wide = high - low
    many = np.tile(ratios, 8)
    low, high = paired_timings.median_interval(many)
    assert high - low < wide


def test_a_failed_run_or_missing_pairs_are_refused(tmp_path):
    with pytest.raises(ValueError, match="no b1.txt"):
        paired_timings.read_pairs(tmp_path)
    (tmp_path / "b1.txt").write_text("Traceback (most recent call last): ...")
    (tmp_path / "a1.txt").write_text("9 frame(s), 1.00 s, 120 Newton iterations")
    with pytest.raises(ValueError, match="b1.txt: no 'N frame"):
        paired_timings.read_pairs(tmp_path)
    with pytest.raises(ValueError, match="as many runs after as before"):
        paired_timings.summarize_pairs([(1.0, 1)], [])


def test_one_alternated_pair_of_the_tiny_fixture(tmp_path, capsys):
    """``run`` with this tree as the tree before too: both runs written, the same Newton iterations, summarized."""
    out = tmp_path / "runs"
    paired_timings.run(REPO, out, 1, ["tests/fixtures/tiny_press.toml", "--frames", "1"])
    before, after = (paired_timings.profile_summary((out / f"{tree}1.txt").read_text()) for tree in "ba")
    assert before[1] == after[1] > 0 and before[0] > 0 and after[0] > 0
    assert "after / before, pair by pair: median" in capsys.readouterr().out
    with pytest.raises(Exception, match="already holds runs"):
        paired_timings.run(REPO, out, 1, ["tests/fixtures/tiny_press.toml", "--frames", "1"])
