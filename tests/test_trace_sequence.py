"""scripts/trace_sequence.py --newton: its count of each frame's Newton steps agrees with the solver's own record."""

import re
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import trace_sequence  # noqa: E402

from transtac_sim.physics import QuasiStaticSolver, device_linear, linear  # noqa: E402

FIXTURES = Path(__file__).resolve().parent / "fixtures"


@pytest.mark.parametrize("lag_moves", [1, 4])
def test_newton_steps_are_split_at_the_first_lag_move(monkeypatch, capsys, lag_moves):
    # the script patches the solver's methods for good: register them so that they are put back after the test
    for owner, names in ((QuasiStaticSolver, ("_hessian", "_move_lag", "_raise_stiffness", "solve_frame",
                                              "_solve_step")),
                         (linear.LinearSolver, ("solve", "_solve_direct")), (device_linear, ("definite_cg",))):
        for name in names:
            monkeypatch.setattr(owner, name, getattr(owner, name))
    monkeypatch.setattr(trace_sequence, "ANATOMY", [trace_sequence._new_frame_counts()])
    monkeypatch.setattr(trace_sequence.faulthandler, "register", lambda *args, **kwargs: None)  # captured stderr
    # the press-and-slide fixture's first three frames: a first touch and two presses with friction 0.5
    trace_sequence.main(FIXTURES / "tiny_press_slide.toml", sequence=0, frames=3, mode="physics",
                        linear_solver="cg", newton=True, friction_lag_moves=lag_moves)
    out = capsys.readouterr().out
    iterations = [int(n) for n in re.findall(r"^frame \d+: [\d.]+ s, (\d+) Newton iterations", out, re.M)]
    moves = len(re.findall(r"friction's lag moved", out))
    rows = [[int(c) for c in line.strip("|").split("|")[1:]] for line in out.splitlines()
            if re.match(r"\| (\d+|1-\d+) \|", line)]
    assert len(iterations) == 3 and len(rows) == 4  # frames 0-2 and the sum over frames 1-2
    for frame, (steps, before, clamped, after, lags) in enumerate(rows[:3]):
        assert steps == iterations[frame] and before + after == steps and 0 <= clamped <= before
        assert lags <= lag_moves  # one sub-step per frame here (each prints its own line)
    assert out.count("sub-step to z") == 3
    assert sum(r[4] for r in rows[:3]) == moves and moves >= 2  # the presses move friction's lag
    assert rows[3] == [sum(r[k] for r in rows[1:3]) for k in range(5)]
    assert rows[1][3] > 0  # a press's lag move costs Newton steps after it
