"""Sphere indentation against Hertz (half-space) and the bonded thin-layer solution (quarter models)."""

import numpy as np
import pytest
import trimesh

from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter
from transtac_sim.physics.analytic import bonded_layer_force, hertz_force
from transtac_sim.physics.box_mesh import box_tet_mesh, graded_coordinates


def quarter_sphere_force(poisson, radius, depth, size, thickness, h_fine, fine, growth, bonded):
    """4 x (-F_z) of a frictionless sphere pressed at the corner x = y = 0 of a quarter block."""
    xs = graded_coordinates(0.0, size, h_fine, 0.0, fine, growth)
    zs = graded_coordinates(0.0, thickness, h_fine, thickness - fine, thickness, growth)
    V, T = box_tet_mesh(xs, xs, zs)
    bottom = V[:, 2] < 1e-9
    fixed = np.stack([V[:, 0] < 1e-9, V[:, 1] < 1e-9, bottom], axis=1)
    if bonded:
        fixed |= bottom[:, None]
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=6, radius=radius))
    solver = QuasiStaticSolver(V, T, ElasticMaterial(1.0, poisson), [sphere], fixed=fixed)
    pose = np.eye(4)
    pose[2, 3] = thickness + radius + 1e-3
    solver.start([pose])
    pose = pose.copy()
    pose[2, 3] = thickness + radius - depth
    res = solver.solve_frame([pose])
    assert res.record.converged and res.record.min_det_f > 0
    return -4.0 * res.forces_n[0, 2], res


@pytest.mark.skip(reason="unverified: the solver takes minutes per frame on 2 cores; see the issue 3 note")
@pytest.mark.slow
@pytest.mark.parametrize("poisson", [0.3, 0.45, 0.49])
def test_hertz_half_space(poisson):
    radius, depth = 5.0, 0.2  # contact radius a = 1 mm; block 40 a deep and wide
    force, res = quarter_sphere_force(poisson, radius, depth, 40.0, 40.0, 0.25, 1.5, 1.8, bonded=False)
    expected = hertz_force(1.0, poisson, radius, depth)
    assert abs(force / expected - 1.0) < 0.03, (force, expected, res.record)


@pytest.mark.skip(reason="unverified: the solver takes minutes per frame on 2 cores; see the issue 3 note")
@pytest.mark.slow
def test_bonded_thin_layer():
    radius, depth, thickness, poisson = 5.0, 0.5, 5.0, 0.49
    force, res = quarter_sphere_force(poisson, radius, depth, 25.0, thickness, 0.3, 2.2, 1.6, bonded=True)
    expected = bonded_layer_force(1.0, poisson, radius, depth, thickness)
    assert abs(force / expected - 1.0) < 0.05, (force, expected, res.record)
