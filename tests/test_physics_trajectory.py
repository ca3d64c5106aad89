"""Trajectory segments -> poses, and press-to-force through the solver."""

import numpy as np
import pytest
import trimesh
from pydantic import TypeAdapter

from transtac_sim.config.trajectory import Segment
from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter
from transtac_sim.physics.box_mesh import gel_block
from transtac_sim.physics.trajectory import IndenterTrajectory, simulate_sequence

SEG = TypeAdapter(Segment)


def _segments(*items):
    return [SEG.validate_python(i) for i in items]


def _sphere(r=2.0):
    return RigidIndenter.from_trimesh("s", trimesh.creation.icosphere(subdivisions=3, radius=r))


def _poses(traj):
    return [p for p, _, _ in traj.frames()]


def test_press_slide_rotate_roll_release_poses():
    ind = _sphere()
    start = np.eye(4)
    start[2, 3] = 5.0 + 2.0 + 0.5
    segs = _segments(
        {"kind": "press", "frames": 4, "depth_mm": 1.0},
        {"kind": "slide", "frames": 2, "direction_deg": 90.0, "distance_mm": 2.0},
        {"kind": "rotate", "frames": 3, "axis": [0, 0, 1], "angle_deg": 90.0},
        {"kind": "roll", "frames": 2, "direction_deg": 0.0, "distance_mm": np.pi},
        {"kind": "release", "frames": 1},
    )
    poses = _poses(IndenterTrajectory(ind, start, segs, 5.0))
    assert len(poses) == 12
    np.testing.assert_allclose(ind.lowest_z(poses[3]), 4.0, atol=1e-9)  # 1 mm below the surface
    np.testing.assert_allclose(poses[1][2, 3] - poses[0][2, 3], -1.5 / 4, atol=1e-12)
    np.testing.assert_allclose(poses[5][:3, 3], [0.0, 2.0, 6.0], atol=1e-12)
    np.testing.assert_allclose(poses[8][:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)  # quarter turn about z
    # rolling pi mm with radius ~2 along +x turns about +y by ~pi/2 and moves the centre pi mm
    radius = poses[8][2, 3] - ind.lowest_z(poses[8])
    np.testing.assert_allclose(poses[10][:3, 3], poses[8][:3, 3] + [np.pi, 0, 0], atol=1e-12)
    turn = poses[10][:3, :3] @ poses[8][:3, :3].T
    np.testing.assert_allclose(turn @ [0, 0, 1], [np.sin(np.pi / radius), 0, np.cos(np.pi / radius)], atol=1e-9)
    np.testing.assert_allclose(poses[11][:3, 3], start[:3, 3], atol=1e-12)  # back to the press start
def test_press_to_force_reaches_target():
    V, T = gel_block(8.0, 8.0, 2.0, h_fine=0.6, fine_half_width=1.5, growth=1.8)
    ind = _sphere()
    from transtac_sim.physics import SolverSettings

    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [ind], SolverSettings(degree=1))
    start = np.eye(4)
    start[2, 3] = 2.0 + 2.0 + 0.05
    segs = _segments({"kind": "press", "frames": 2, "force_n": 0.2})
    results = list(simulate_sequence(solver, [start], [segs], 2.0))
    forces = [-r.forces_n[0, 2] for r in results]
    np.testing.assert_allclose(forces, [0.1, 0.2], rtol=0.011)


def test_press_to_force_beside_the_gel_says_it_never_touched():
    """A sphere 8 mm beside the edge of an 8 mm block, pressed to a force: every secant trial gives 0 N."""
    from transtac_sim.physics import SolverDidNotConverge, SolverSettings

    V, T = gel_block(8.0, 8.0, 2.0, h_fine=1.0, fine_half_width=1.0, growth=1.8)
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [_sphere()], SolverSettings(degree=1))
    start = np.eye(4)
    start[:3, 3] = [14.0, 0.0, 2.0 + 2.0 + 0.05]
    segs = _segments({"kind": "press", "frames": 1, "force_n": 0.2})
    with pytest.raises(SolverDidNotConverge, match="'s' never touched the gel"):
        list(simulate_sequence(solver, [start], [segs], 2.0, max_force_trials=4))
