"""scripts/paired_timings.py: the paired comparison of two trees' profile runs, against ratios known by construction,
and one alternated run of the tiny fixture."""

import sys
from pathlib import Path

import numpy as np
import pytest
import typer

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


def _stub_tree(root: Path, name: str, order: Path) -> Path:
    """A tree whose transtac_sim says where it was imported from, whose profile prints a summary line and appends the
    tree's name to ``order``."""
    (root / "transtac_sim").mkdir(parents=True)
    (root / "transtac_sim" / "__init__.py").write_text(f"TREE = {name!r}\n")
    (root / "scripts").mkdir()
    (root / "scripts" / "fem_phase_profile.py").write_text(
        "import sys, transtac_sim\n"
        f"open({str(order)!r}, 'a').write(transtac_sim.TREE + '\\n')\n"
        "print(transtac_sim.TREE, transtac_sim.__file__, sys.argv[1:])\n"
        "print('x on cpu: 1 frame(s), 1.00 s, 8 Newton iterations')\n")
    return root


def test_each_run_imports_its_own_tree(tmp_path, monkeypatch):
    """``run`` puts the tree before first on PYTHONPATH and runs its own profile (not the installed package), the
    profile's arguments passed on, the order swapped in every other pair; a run without a summary line is refused."""
    order = tmp_path / "order.log"
    before = _stub_tree(tmp_path / "before", "before", order)
    after = _stub_tree(tmp_path / "after", "after", order)
    monkeypatch.setattr(paired_timings, "REPO", after)
    out = tmp_path / "runs"
    paired_timings.run(before, out, 2, ["scene.toml", "--frames", "1"])
    for k in (1, 2):
        b, a = ((out / f"{tree}{k}.txt").read_text() for tree in "ba")
        assert b.startswith("before " + str(before / "transtac_sim" / "__init__.py")), b
        assert a.startswith("after " + str(after / "transtac_sim" / "__init__.py")), a
        assert "['scene.toml', '--frames', '1']" in b and "['scene.toml', '--frames', '1']" in a
    assert order.read_text().split() == ["before", "after", "after", "before"]  # the second pair's order swapped
    (before / "scripts" / "fem_phase_profile.py").write_text("print('no summary')\n")
    with pytest.raises(typer.Exit):
        paired_timings.run(before, tmp_path / "failed", 1, [])
    with pytest.raises(typer.BadParameter, match="has no transtac_sim"):
        paired_timings.run(tmp_path / "nowhere", tmp_path / "none", 1, [])


@pytest.mark.slow
def test_one_alternated_pair_of_the_tiny_fixture(tmp_path, capsys):
    """``run`` with this tree as the tree before too, on the real profile: both runs written, the same Newton
    iterations, summarized; a folder that holds runs is refused."""
    out = tmp_path / "runs"
    paired_timings.run(REPO, out, 1, ["tests/fixtures/tiny_press.toml", "--frames", "1"])
    before, after = (paired_timings.profile_summary((out / f"{tree}1.txt").read_text()) for tree in "ba")
    assert before[1] == after[1] > 0 and before[0] > 0 and after[0] > 0
    assert "after / before, pair by pair: median" in capsys.readouterr().out
    with pytest.raises(typer.BadParameter, match="already holds runs"):
        paired_timings.run(REPO, out, 1, ["tests/fixtures/tiny_press.toml", "--frames", "1"])
