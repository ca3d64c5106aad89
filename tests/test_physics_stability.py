"""Stability on stiff and extreme cases, fast versions of scripts/fem_stability.py (same cases and runner).

A coarse 6 x 6 x 3 mm P2 block; every case must converge (or fail with the specific, clear error), keep
every displacement finite and det F > 0 in every frame, and pass one cheap physical check, with Newton's step-length
test alone (SolverSettings' default) and with the force test scenes take (config/scene.py ``newton_force_rtol``).
"""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import fem_stability as fs  # noqa: E402

from transtac_sim.physics import IndenterStartsInsideGel  # noqa: E402

BLOCK = fs.Block(width=6.0, thickness=3.0, h_fine=1.0, fine_half_width=2.0)


@pytest.fixture(params=[None, 3e-3], ids=["step_test", "force_test"])
def force_rtol(request) -> float | None:
    """Newton's force test (SolverSettings.newton_force_rtol): off, and the scenes' default."""
    return request.param


def _case(name: str, **changes) -> fs.Case:
    (case,) = [c for c in fs.cases() if c.name == name]
    return replace(case, **changes)


def _check_frames(r: fs.CaseResult) -> None:
    """Every reported frame: converged, finite, det F > 0, penetration within the stated tolerance."""
    case = r.case
    for k, f in enumerate(r.frames):
        assert f["converged"], (case.name, k)
        assert f["finite"], (case.name, k)
        assert f["min_det_f"] > 0.0, (case.name, k, f["min_det_f"])
        assert f["max_penetration_mm"] <= 0.02 + 1e-9


def _run_ok(case: fs.Case, force_rtol: float | None) -> fs.CaseResult:
    r = fs.run_case(case, BLOCK, newton_force_rtol=force_rtol)
    assert r.error is None, f"{case.name}: {r.error}"
    expected_frames = len(fs.trajectory(case, fs.make_indenter(case.shape, BLOCK.thickness, 0.0), BLOCK.thickness)[1])
    assert len(r.frames) == expected_frames
    _check_frames(r)
    return r


def _press_force_increases(r: fs.CaseResult) -> None:
    fz = np.array([f["fz"] for f in r.frames])
    assert np.all(fz < 0.0) and np.all(np.diff(-fz) > 0.0), fz  # pressing harder, pushing the gel down


@pytest.mark.parametrize("young", [0.05, 5.0])
@pytest.mark.parametrize("poisson", [0.3, 0.499])
def test_materials_press_30_percent(poisson, young, force_rtol):
    r = _run_ok(_case("nu = 0.45", poisson=poisson, young_mpa=young), force_rtol)
    _press_force_increases(r)


def test_stiff_backing_barely_moves(force_rtol):
    r = _run_ok(_case("gel on a 1000x stiffer backing", depth=0.2), force_rtol)
    _press_force_increases(r)
    last = r.frames[-1]
    assert last["max_u_backing_mm"] < 1e-2 * last["max_u_mm"], last


def test_cube_edge(force_rtol):
    _press_force_increases(_run_ok(_case("cube edge, 30 %"), force_rtol))


def test_cone_tip(force_rtol):
    """The pressure concentrates at the tip: the solver raises the contact stiffness until the penetration
    is within the stated 0.02 mm (checked for every frame by _run_ok)."""
    _press_force_increases(_run_ok(_case("cone tip, 30 %"), force_rtol))


def test_slide_with_friction_one_obeys_coulomb(force_rtol):
    case = _case("slide mu = 1.0 (20 % deep, 4 x 0.5 mm)")
    r = _run_ok(case, force_rtol)
    slide = r.frames[-case.slide_frames:]
    for f in slide:  # fx also holds the normal traction's x part (ploughing: the rim in front is steeper):
        assert abs(f["fx"]) <= case.friction * abs(f["fz"]) * 1.1, f  # seen: |fx| / mu |fz| up to 1.05
    assert slide[-1]["fx"] > 0.05 * abs(slide[-1]["fz"])  # the indenter moving along +x drags the gel along +x


def test_start_inside_is_a_clear_error():
    case = _case("starts 1 mm inside the gel")
    r = fs.run_case(case, BLOCK)
    assert isinstance(r.error, IndenterStartsInsideGel) and not r.frames
    msg = str(r.error)
    assert "'sphere'" in msg and "inside the undeformed gel" in msg and "start it above" in msg
