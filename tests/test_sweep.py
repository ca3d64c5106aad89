"""`transtac-sim sweep`: bad sweep files end with one line naming the key; the FEM cache replays another
layout's markers exactly as a fresh solve gives them; a small sweep runs end to end with one FEM solve for
all its points, shares images between points that differ only in pipeline settings, records a failing
point with its reason, writes one table row per point with finite metrics, and resumes without
recomputing finished points."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from transtac_sim.cli import app
from transtac_sim.config import ConfigError
from transtac_sim.sweep import mechanics, point_scenes, run
from transtac_sim.sweep.config import lattice_pitch, load_sweep
from transtac_sim.sweep.report import pareto_front

FIXTURES = Path(__file__).parent / "fixtures"

# the tiny test sensor with 320x240 cameras: the blob detector finds its 0.4 mm markers
SENSOR = (FIXTURES / "tiny_sensor.toml").read_text().replace("image_size = [96, 72]", "image_size = [320, 240]")

SWEEP = """
name = "tiny"
[parameters]
count = [10, 16]
min_spacing_mm = 3.0
radius_mm = 0.4
detector = ["blob", "learned"]
[benchmark]
frames = 2
press_depth_mm = 0.6
motions = [{ kind = "press", indenter = "sphere_r4" }]
[scene]
hardware = "sensor.toml"
mesh = { edge_mm = 3.0, contact_edge_mm = 1.5, refine_margin_mm = 1.0 }
physics = { degree = 1 }
render = { spp = 4 }
"""


def _write(tmp_path: Path, text: str = SWEEP, name: str = "sweep.toml") -> Path:
    (tmp_path / "sensor.toml").write_text(SENSOR)
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize("old, new, key, words", [
    ("radius_mm = 0.4", "radius_mm = 0.4\ncolour = [1, 2]", "parameters.colour", "unknown parameter"),
    ("count = [10, 16]", "count = []", "parameters.count", "empty range"),
    ("[parameters]", "[search]\nkind = \"random\"\nsamples = 3\n[parameters]\nseed = { low = 5, high = 1 }",
     "parameters.seed", "empty range"),
    ("count = [10, 16]", "count = [10, 400]", "parameters.count", "only"),  # 400 do not fit at 3 mm spacing
    ("count = [10, 16]", "count = [10, 400]\npattern = \"grid\"", "parameters.count", "closer than min_spacing_mm"),
    ("radius_mm = 0.4", "radius_mm = 0.4\ndepth_mm = [0.6, 4.9]", "parameters.depth_mm", "do not fit"),
    ("frames = 2", "frames = 2\nsize = 3", "benchmark.size", "unknown key"),
    ("radius_mm = 0.4", "radius_mm = [0.4, nan]", "parameters.radius_mm", "nan is not a (finite) number"),
])
def test_bad_sweep_file_is_one_line_naming_the_key(tmp_path: Path, old: str, new: str, key: str, words: str):
    path = _write(tmp_path, SWEEP.replace(old, new, 1))
    with pytest.raises(ConfigError) as e:
        load_sweep(path)
    assert len(e.value.problems) == 1
    assert e.value.problems[0][0] == key and words in e.value.problems[0][1], e.value.problems
    res = CliRunner().invoke(app, ["sweep", str(path), "--out", str(tmp_path / "out")])
    lines = res.output.splitlines()
    assert res.exit_code == 2 and len(lines) == 1 and key in lines[0] and str(path) in lines[0], res.output
    assert not (tmp_path / "out").exists()  # nothing computed, nothing written


def test_grid_and_random_expansion(tmp_path: Path):
    s = load_sweep(_write(tmp_path))
    assert len(s.points) == 4 and s.swept == ["count", "detector"]
    assert {(p.values["count"], p.values["detector"]) for p in s.points} == {(10, "blob"), (10, "learned"), (16, "blob"), (16, "learned")}
    r = load_sweep(_write(tmp_path, SWEEP.replace("[parameters]", "[search]\nkind = \"random\"\nsamples = 5\nseed = 3\n[parameters]\n"
                                                  "depth_mm = { low = 0.5, high = 1.5 }"), "random.toml"))
    depths = [p.values["depth_mm"] for p in r.points]
    assert len(r.points) == 5 and all(0.5 <= d <= 1.5 for d in depths) and len(set(depths)) == 5


def test_lattice_pitch_gives_the_closest_count():
    from transtac_sim.config.hardware import GridLayout
    from transtac_sim.sensor.layouts import lattice_xy

    p = lattice_pitch("grid", 48, (32.0, 24.0), 1.0)
    n = len(lattice_xy(GridLayout(layout="grid", pitch_mm=p, radius_mm=0.2, depth_mm=1.0), (32.0, 24.0), np.random.default_rng(0)))
    assert abs(n - 48) <= 4, (p, n)


def test_pareto_front():
    markers = np.array([40, 80, 120, 80, 40])
    error = np.array([0.10, 0.08, 0.09, 0.20, np.nan])
    assert pareto_front(markers, error).tolist() == [1, 2]  # 0 is beaten by 1; 3 by 1; 4 has no error


def test_fem_cache_replays_another_layout_exactly(tmp_path: Path):
    """The cached field (vertex + edge-midpoint displacements) gives the solver's own marker positions, for
    the layout that was solved and for another one (checked against a second, fresh solve)."""
    from transtac_sim.dataset.sequence import StageClock
    from transtac_sim.simulation import simulate_frames

    s = load_sweep(_write(tmp_path))
    a, b = (next(p for p in s.points if p.values["count"] == n) for n in (10, 16))
    setup_a = point_scenes.point_setups(s, a.values, tmp_path)[0]
    setup_b = point_scenes.point_setups(s, b.values, tmp_path)[0]
    assert mechanics.mechanics_key(setup_a, 2) == mechanics.mechanics_key(setup_b, 2)  # markers are not mechanics
    cache = mechanics.FemCache(tmp_path / "fem")
    assert cache.solve(setup_a, 2)["status"] == "done"
    with np.load(cache.path(mechanics.mechanics_key(setup_a, 2))) as z:
        solved = z["markers_solved"]
    frames_a, _ = cache.replay(setup_a, 2)
    for f, ph in enumerate(frames_a):
        assert np.abs(ph.markers_gel_mm - solved[f]).max() < 1e-9
    fresh = list(simulate_frames(setup_b, 2, StageClock()))
    replayed, _ = cache.replay(setup_b, 2)
    moved = np.abs(fresh[-1].markers_gel_mm - setup_b.sensor.markers_rest_gel_mm).max()
    assert moved > 0.01  # the press moves the markers...
    for x, y in zip(fresh, replayed, strict=True):  # ...and the replay puts them where a solve does
        assert np.abs(x.markers_gel_mm - y.markers_gel_mm).max() < 1e-6 * max(moved, 1.0)
        np.testing.assert_allclose(x.surface_vertices_gel_mm, y.surface_vertices_gel_mm, atol=1e-9)
        np.testing.assert_allclose(np.asarray(x.forces_n), np.asarray(y.forces_n), atol=1e-9)


def test_small_sweep_end_to_end_reuse_and_resume(tmp_path: Path, monkeypatch):
    path = _write(tmp_path)
    out = tmp_path / "out"
    fem_calls = []
    real = mechanics.simulate_frames

    def counting(setup, frames, clock):
        fem_calls.append(setup.scene.name)
        return real(setup, frames, clock)

    monkeypatch.setattr(mechanics, "simulate_frames", counting)
    rep = run.run_sweep(path, out)
    # one FEM solve for 4 points (2 layouts x 2 detectors): a layout-only change does not call the FEM again
    assert len(fem_calls) == 1 and rep.fem_solves == 1 and rep.fem_shared == 3
    # 2 image sets (one per layout); each is scored by its 2 detector settings
    assert rep.renders == 2 and rep.render_shared == 2
    assert _reuse(out)["frames_rendered_now"] == 4  # 2 sets x 1 motion x 2 frames
    rows = {r["point"]: r for r in _csv(rep.table)}
    assert len(rows) == 4
    ok = [r for r in rows.values() if r["detector"] == "blob"]
    bad = [r for r in rows.values() if r["detector"] == "learned"]
    # the learned detector only takes its training size: recorded with its reason, the sweep went on
    assert all(r["status"] == "failed" and "320x240" in r["reason"] for r in bad), bad
    assert all(r["status"] == "done" for r in ok) and rep.done == 2
    for r in ok:
        for k in ("detection_recall", "detection_precision", "correct_matches_per_frame", "match_precision",
                  "tracking_idf1", "reconstruction_error_mm", "seconds_detect_per_frame", "fem_seconds", "render_seconds"):
            assert math.isfinite(float(r[k])), (k, r[k])
        assert float(r["detection_recall"]) > 0.5 and float(r["correct_matches_per_frame"]) > 3
        assert float(r["reconstruction_error_mm"]) < 0.5
    assert {int(r["markers"]) for r in ok} == {10, 16}
    html = rep.report_html.read_text()
    assert "<img" in html and "3 pair(s) reused a solve of another point" in html
    assert all(p.is_file() for p in rep.plots) and any("pareto" in p.name for p in rep.plots)

    # resume: nothing finished is recomputed (no FEM, no render); the failed points are tried again
    fem_calls.clear()
    renders = []
    real_render = run._render_set
    monkeypatch.setattr(run, "_render_set", lambda *a: renders.append(1) or real_render(*a))
    done_before = {p: (out / "points").joinpath(p).stat().st_mtime_ns for p in _done_keys(out)}
    rep2 = run.run_sweep(path, out)
    assert rep2.resumed == 2 and fem_calls == [] and rep2.fem_cached == 1
    assert _reuse(out)["frames_rendered_now"] == 0  # the failed points' images were all on disk
    assert {p: (out / "points").joinpath(p).stat().st_mtime_ns for p in _done_keys(out)} == done_before
    assert len(_csv(rep2.table)) == 4
    # an interrupted sweep: one finished point's result lost -> only that point is scored again, from the
    # images already rendered (no FEM, no new frame); this time as a Ray task
    pytest.importorskip("ray")
    lost = _done_keys(out)[0]
    (out / "points" / lost / "result.json").unlink()
    rep3 = run.run_sweep(path, out, executor="ray")
    assert rep3.resumed == 1 and rep3.fem_solves == 0 and rep3.fem_cached == 1 and rep3.done == 2
    again = json.loads((out / "points" / lost / "result.json").read_text())
    assert again["status"] == "done" and again["render_reused"] is True


def _reuse(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())["reuse"]


def _done_keys(out: Path) -> list[str]:
    return sorted(p.parent.name for p in (out / "points").glob("*/result.json")
                  if json.loads(p.read_text())["status"] == "done")


def _csv(path: Path) -> list[dict]:
    import csv

    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def test_what_changes_the_mechanics_and_what_the_images(tmp_path: Path):
    """Gel thickness and stiffness change the FEM key; marker layout and camera baseline do not (they change
    the images); pipeline settings change neither. A thickness or baseline is written as a hardware copy."""
    text = SWEEP.replace("detector = [\"blob\", \"learned\"]",
                         "thickness_mm = [5.0, 4.0]\nyoungs_modulus_mpa = [0.3, 0.5]\nbaseline_mm = [12.0, 10.0]\n"
                         "depth_mm = [0.6, 1.0]\nmatcher = [\"delaunay\", \"hungarian\"]")
    s = load_sweep(_write(tmp_path, text))
    assert len(s.points) == 2 ** 6

    def keys(values):
        setup = point_scenes.point_setups(s, values, tmp_path)[0]
        return mechanics.mechanics_key(setup, 2), point_scenes.render_key(s, values), setup

    base = s.points[0].values
    k0, r0, setup0 = keys(base)
    assert setup0.sensor.gel_size_mm[2] == 5.0 and setup0.sensor.cameras["right"].T[0] == -12.0
    for change, same_fem, same_images in [({"count": 16}, True, False), ({"depth_mm": 1.0}, True, False),
                                          ({"baseline_mm": 10.0}, True, False), ({"matcher": "hungarian"}, True, True),
                                          ({"thickness_mm": 4.0}, False, False), ({"youngs_modulus_mpa": 0.5}, False, False)]:
        k, r, setup = keys({**base, **change})
        assert (k == k0, r == r0) == (same_fem, same_images), change
    _, _, thin = keys({**base, "thickness_mm": 4.0, "baseline_mm": 10.0})
    assert thin.sensor.gel_size_mm[2] == 4.0 and thin.sensor.cameras["right"].T[0] == -10.0
    assert len(list((tmp_path / "hardware").glob("*.toml"))) == 3  # baseline 10; thickness 4; both
