"""scripts/trace_sequence.py: --newton's count of each frame's Newton steps agrees with the solver's own record;
--warm-start-distance measures the distances it prints; --curvature's directions have the curvature the Hessians'
construction gives them (elasticity.py); and the Newton variants of scripts/solver_variants.py do what they say."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest
import typer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import trace_sequence  # noqa: E402

from transtac_sim.physics import QuasiStaticSolver, device_linear, friction_lag, linear  # noqa: E402
from transtac_sim.physics.device_linear import DeviceSolves  # noqa: E402
from transtac_sim.physics.newton import NewtonSteps  # noqa: E402
from transtac_sim.physics.warm_start import WarmStart  # noqa: E402

FIXTURES = Path(__file__).resolve().parent / "fixtures"
NUMBER = r"(-?[\d.]+(?:e[-+]\d+)?)"


def _restore_after(monkeypatch):
    """The script patches the solver's methods for good: register them so that they are put back after the test."""
    for owner, names in ((QuasiStaticSolver, ("_hessian", "_move_lag", "_raise_stiffness", "solve_frame",
                                              "_solve_step")),
                         (linear.LinearSolver, ("solve", "_solve_direct")), (device_linear, ("definite_cg",)),
                         (DeviceSolves, ("_solve_cg",)), (WarmStart, ("_guesses", "_warm_start", "_carried"))):
        for name in names:
            monkeypatch.setattr(owner, name, getattr(owner, name))
    monkeypatch.setattr(trace_sequence, "ANATOMY", [trace_sequence._new_frame_counts()])
    monkeypatch.setattr(trace_sequence.faulthandler, "register", lambda *args, **kwargs: None)  # captured stderr


@pytest.mark.parametrize("lag_moves", [1, 4])
def test_newton_steps_are_split_at_the_first_lag_move(monkeypatch, capsys, lag_moves):
    _restore_after(monkeypatch)
    # the press-and-slide fixture's first three frames: a first touch and two presses with friction 0.5
    trace_sequence.main(FIXTURES / "tiny_press_slide.toml", sequence=0, frames=3, mode="physics",
                        linear_solver="cg", newton=True, friction_lag_moves=lag_moves, warm_start_distance=False,
                        warm_start="all", curvature=False)
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


def test_warm_start_distances_and_curvatures(monkeypatch, capsys):
    _restore_after(monkeypatch)
    solutions, axes = {}, {}  # per frame: the converged dof values and the indenter's target axis (x, y), mm
    solve_frame = QuasiStaticSolver.solve_frame

    def kept(self, poses):
        frame = self.frame_index
        result = solve_frame(self, poses)
        solutions[frame], axes[frame] = self.u.dof_values.numpy().copy(), np.asarray(poses[0])[:2, 3]
        return result

    monkeypatch.setattr(QuasiStaticSolver, "solve_frame", kept)
    # frames 0-5 of the press-and-slide fixture: frames 4 and 5 slide (the carried guess alone: --warm-start carried)
    trace_sequence.main(FIXTURES / "tiny_press_slide.toml", sequence=0, frames=6, mode="physics",
                        linear_solver="cg", newton=True, friction_lag_moves=None, warm_start_distance=True,
                        warm_start="carried", curvature=True)
    out = capsys.readouterr().out
    steps = {}  # frame -> its sub-steps' (last state, start, guesses) distance triples
    for frame, last_state, start, guesses in re.findall(
            r"^    frame (\d+), from the solution .*last state ([^,]*), start ([^,]*), guesses ?(.*)$", out, re.M):
        triples = [tuple(float(v) for v in t.split(" / ")) for t in [last_state, start] + guesses.split(", ") if t]
        assert all(q90 <= q99 <= largest for q90, q99, largest in triples)
        assert triples[1] in [triples[0], *triples[2:]]  # the start is the last state or one of the guesses
        steps.setdefault(int(frame), []).append(triples)
    assert sorted(steps) == list(range(6))
    for frame in range(1, 6):
        if len(steps[frame]) == 1:  # one sub-step: its last state is the last frame's solution
            change = np.linalg.norm(solutions[frame] - solutions[frame - 1], axis=1).max()
            assert steps[frame][0][0][2] == pytest.approx(change, abs=6e-4)
    slide = steps[5][0]  # frame 5 slides on: the carried guess alone ("all" makes two here), and it is taken
    assert len(slide) == 3 and slide[1] == slide[2] != slide[0]
    curvatures = re.findall(rf"^    frame (\d+), p \. H p .*exact {NUMBER}, clamped {NUMBER}, Gauss-Newton {NUMBER}; "
                            rf"its 10 largest nodes carry (\d+)% of \|p\|\^2, at depth \[([^\]]*)\] mm, .* from "
                            rf"the indenter's axis at \({NUMBER}, {NUMBER}\) mm$", out, re.M)
    refused = re.findall(r"Newton system, exact Hessian: not positive definite", out)
    on_preconditioner = re.findall(r"CG stopped where its preconditioner is not positive definite", out)
    assert curvatures and len(curvatures) + len(on_preconditioner) == len(refused)  # each refusal told once
    for frame, exact, clamped, gauss_newton, share, depths, x, y in curvatures:
        exact, clamped, gauss_newton = float(exact), float(clamped), float(gauss_newton)
        # CG stopped at p . A p <= 0 (A: the matrix rounded to float32, whose round-off float64 may see past); the
        # clamped and Gauss-Newton Hessians are positive semi-definite tet by tet (elasticity.py), contact's too
        assert exact <= 1e-4 * gauss_newton and 0.0 <= clamped and 0.0 < gauss_newton
        assert exact < clamped and 0 < int(share) <= 100
        assert all(float(d) >= 0.0 for d in depths.split(","))
        assert (float(x), float(y)) == pytest.approx(tuple(axes[int(frame)]), abs=1e-3)  # the sub-step's target


def test_carried_warm_start_only_where_a_single_indenter_slides():
    solver_variants = trace_sequence.solver_variants
    settings = type("Settings", (), {"newton_tol_mm": 1e-4})()

    def guesses_of(indenters: int, step):
        stub = type("Stub", (), {"indenters": [None] * indenters, "settings": settings,
                                 "_carried": lambda self, shift: ("carried", *shift)})()
        return solver_variants._carried_on_slides(stub, lambda self, step: ["all"], np.array(step, dtype=float))

    assert guesses_of(1, [0.5, 0.0, 0.0, 0, 0, 0]) == [("carried", 0.5, 0.0, 0.0)]  # a slide: that guess alone
    assert guesses_of(1, [0.5, 0.0, -0.1, 0, 0, 0]) == [("carried", 0.5, 0.0, 0.0)]  # sliding deeper: the same
    assert guesses_of(1, [0.0, 0.0, -0.3, 0, 0, 0]) == ["all"]  # a press
    assert guesses_of(1, [0.5, 0.0, 0.3, 0, 0, 0]) == ["all"]  # moving away from the gel: the unload guesses too
    assert guesses_of(2, [0.5, 0.0, 0.0, 0, 0, 0, 0.5, 0.0, 0.0, 0, 0, 0]) == ["all"]  # two indenters: no carried guess


def test_press_lag_move_ratio_only_on_presses_that_may_move_the_lag_again(monkeypatch):
    """solver_variants ``--press-lag-move-ratio`` (BENCHMARKS.md ``fem_press_lag_moves_gpu``): ``presses_only`` tells a
    press from a slide, a turn, a lift and a hold; the lag threshold takes the press ratio on such a load step where the
    lag may move more than once, and friction_lag.LAG_MOVE_RATIOS elsewhere."""
    solver_variants, tol = trace_sequence.solver_variants, 1e-4
    assert solver_variants.presses_only(np.array([0, 0, -0.1, 0, 0, 0.0]), tol)
    assert solver_variants.presses_only(np.array([0, 0, -0.1, 0, 0, 0, 0, 0, 0, 0, 0, 0.0]), tol)  # the other holds
    assert solver_variants.presses_only(np.array([5e-5, 0, -0.1, 0, 0, 0.0]), tol)  # sideways within the tolerance
    for step in ([0.01, 0, -0.1, 0, 0, 0], [0, 0, -0.1, 0, 0.01, 0], [0, 0, 0.1, 0, 0, 0], [0, 0, 0, 0, 0, 0],
                 [0, 0, -0.1, 0, 0, 0, 0.1, 0, 0, 0, 0, 0]):  # slides, turns, lifts, holds; the other one slides
        assert not solver_variants.presses_only(np.array(step, dtype=float), tol), step

    class Stub:
        def __init__(self, step, lag_moves: int):
            self.settings = type("Settings", (), {"newton_tol_mm": tol, "friction_lag_moves": lag_moves})()
            self._linear = type("Linear", (), {"method": "cg"})()
            self._step = np.array(step, dtype=float)

        def _pose_step(self, prev_poses, poses):
            return self._step

    monkeypatch.setattr(NewtonSteps, "_solve_step", lambda self, poses, prev_poses, may_stall=False: "solved")
    monkeypatch.setattr(NewtonSteps, "_lag_threshold", NewtonSteps._lag_threshold)
    solver_variants._moves_lag_at_on_presses(1.0)
    slide_ratio = friction_lag.LAG_MOVE_RATIOS["cg"]
    for step, lag_moves, ratio in (([0, 0, -0.1, 0, 0, 0], 4, 1.0), ([0.1, 0, 0, 0, 0, 0], 4, slide_ratio),
                                   ([0, 0, -0.1, 0, 0, 0], 1, slide_ratio)):
        stub = Stub(step, lag_moves)
        assert NewtonSteps._solve_step(stub, None, None) == "solved"
        assert NewtonSteps._lag_threshold(stub, 0.01) == pytest.approx(max(tol, ratio * 0.01)), (step, lag_moves)
        assert NewtonSteps._lag_threshold(stub, 5 * tol) is None  # within 10 newton_tol_mm: the lag stays


def test_oracle_lag_starts_each_step_from_the_recorded_solution(monkeypatch):
    """solver_variants ``--save-step-solutions`` / ``--oracle-lag`` (BENCHMARKS.md ``fem_oracle_lag_gpu``): a run with a
    converged lag keeps each step's poses and solution; a second run takes that solution as each step's friction lag
    where Newton starts, never moves it, and ends at the recorded solution; a run whose steps differ is refused."""
    import dataclasses

    from transtac_sim.dataset.sequence import StageClock
    from transtac_sim.scene_setup import load_setup
    from transtac_sim.simulation import simulate_frames

    solver_variants = trace_sequence.solver_variants
    for name in ("_solve_step", "_newton", "_move_lag", "_lag_change", "_read_gradient"):
        monkeypatch.setattr(NewtonSteps, name, getattr(NewtonSteps, name))
        if name in vars(QuasiStaticSolver):  # a copy that another script's restore left on the subclass would hide
            monkeypatch.delattr(QuasiStaticSolver, name)  # the variants' patches of NewtonSteps (put back after)
    setup = load_setup(FIXTURES / "tiny_press_slide.toml")

    def run(frames: int, lag_moves: int) -> list:
        physics = setup.scene.physics.model_copy(update={"linear_solver": "direct", "friction_lag_moves": lag_moves})
        scene = setup.scene.model_copy(update={"physics": physics})
        return list(simulate_frames(dataclasses.replace(setup, scene=scene), frames, StageClock()))

    solve_step = NewtonSteps._solve_step
    kept = solver_variants.keep_step_solutions()
    recorded = run(3, 12)  # a first touch and two presses with friction 0.5, the lag converged
    NewtonSteps._solve_step = solve_step
    assert len(kept) == 3 and all(f.solver["substeps"] == 1 for f in recorded)
    poses, solutions = np.stack([p for p, _ in kept]), np.stack([u for _, u in kept])
    assert np.abs(solutions[2]).max() > 0.5  # the press has moved the gel

    starts, ends = [], []  # per step: the largest distance of friction's lag from the recorded solution where
    newton_steps = NewtonSteps._newton  # Newton starts and where it ends

    def spied(self, ind, may_stall=False, lifting=False):
        k = len(starts)
        starts.append(np.abs(self.u_lag.dof_values.numpy() - solutions[k]).max())
        result = newton_steps(self, ind, may_stall, lifting)
        ends.append(np.abs(self.u_lag.dof_values.numpy() - solutions[k]).max())
        return result

    NewtonSteps._newton = spied
    move_lag, lag_change, read_gradient = NewtonSteps._move_lag, NewtonSteps._lag_change, NewtonSteps._read_gradient
    solver_variants.oracle_lag(poses, solutions)
    oracle = run(3, 4)
    assert starts == [0.0, 0.0, 0.0] and ends == [0.0, 0.0, 0.0]  # set where Newton starts, never moved
    for a, b in zip(recorded, oracle, strict=True):
        assert np.abs(a.markers_gel_mm - b.markers_gel_mm).max() < 1e-3  # Newton's tolerance 1e-4 mm, lag within 1e-3
    NewtonSteps._solve_step, NewtonSteps._newton = solve_step, newton_steps
    NewtonSteps._move_lag, NewtonSteps._lag_change, NewtonSteps._read_gradient = move_lag, lag_change, read_gradient
    _one_part_of_the_lag_from_the_recorded_solution(solver_variants, run, recorded, poses, solutions)
    shifted = poses.copy()
    shifted[1, :, 2, 3] -= 0.01
    solver_variants.oracle_lag(shifted, solutions)
    with pytest.raises(RuntimeError, match="load step 1 of this run goes to other poses"):
        run(2, 4)


def _one_part_of_the_lag_from_the_recorded_solution(solver_variants, run, recorded, poses, solutions):
    """``--oracle-lag-part pressure|normal`` (BENCHMARKS.md ``fem_lag_pressure_oracle``): where Newton starts, that part
    of friction's lag (the penetration lag_g or the normal lag_n) is the recorded solution's and the other is the
    solver's own; u_lag stays the solver's own (the recorded solution only where the step starts there), the lag then
    moves as by default, and the run ends at the recorded solution; each step's first-lag penetration error is
    returned, 0 where it agrees with the recorded one."""
    for part, recorded_name, own_name in (("pressure", "lag_g", "lag_n"), ("normal", "lag_n", "lag_g")):
        seen, moves, errors, frames = _run_with_one_part(solver_variants, run, poses, solutions, part)
        assert [s[recorded_name] for s in seen] == [True, True, True], part
        # the solver's own first lag differs from the recorded one where the gel touches (frames 1-2), and it moves
        assert [s[own_name] for s in seen[1:]] == [False, False], part
        assert not any(s["u_lag"] for s in seen[1:]) and sum(moves) > 0, part
        assert len(errors) == 3 and all(e > 0.05 for e in errors[1:]), (part, errors)
        for a, b in zip(recorded, frames, strict=True):
            assert np.abs(a.markers_gel_mm - b.markers_gel_mm).max() < 1e-3, part
    with pytest.raises(typer.BadParameter, match="--oracle-lag-part must be one of"):
        solver_variants.oracle_lag(poses, solutions, "tangent")


def _run_with_one_part(solver_variants, run, poses, solutions, part):
    """3 frames with ``oracle_lag(..., part)``: per step whether lag_g, lag_n and u_lag are the recorded solution's
    where Newton starts, the frame's lag moves after each step, the first-lag penetration errors, and the frames."""
    solve_step, newton_steps, update_lag = NewtonSteps._solve_step, NewtonSteps._newton, QuasiStaticSolver._update_lag
    seen, moves, errors = [], [], []

    def spied(self, ind, may_stall=False, lifting=False):
        k = len(seen)
        st = self._contact_state
        kept = {name: getattr(st, name).numpy().copy() for name in ("lag_g", "lag_n")}
        self._u_try.dof_values.assign(solutions[k])
        update_lag(self, ind, self._u_try)  # the recorded solution's lag
        seen.append({name: np.array_equal(kept[name], getattr(st, name).numpy()) for name in kept}
                    | {"u_lag": np.array_equal(self.u_lag.dof_values.numpy(), solutions[k])})
        st.lag_g.assign(kept["lag_g"])
        st.lag_n.assign(kept["lag_n"])
        result = newton_steps(self, ind, may_stall, lifting)
        moves.append(self.stats["lag_updates"])
        return result

    NewtonSteps._newton = spied
    solver_variants.oracle_lag(poses, solutions, part, errors)
    try:
        frames = run(3, 4)
    finally:
        NewtonSteps._solve_step, NewtonSteps._newton = solve_step, newton_steps
    return seen, moves, errors, frames
