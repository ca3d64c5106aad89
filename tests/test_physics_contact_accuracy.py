"""Sphere indentation against Hertz (half-space) and the bonded thin-layer solution (quarter models).

A frictionless rigid sphere is pressed at the corner x = y = 0 of a quarter block (u_x = 0 on x = 0,
u_y = 0 on y = 0: exact by symmetry), the total force is 4 x (-F_z), compared with the closed forms of
``physics/analytic.py`` without any correction factor. P2 elements (the default order). E = 1 MPa.

Measured (2-core CPU, about 3 min for the file): Hertz +0.2 % (nu 0.3), -1.6 % (0.45), -1.9 % (0.49); bonded
layer -1.5 % (d 0.1 mm) and +0.3 % (d 0.25 mm) (against the bonded coefficients as corrected in issue 12:
the earlier, wrong ones put the reference 0.7 % and 0.6 % lower, and the errors at -0.7 % and +0.9 %).

Error sources and how each is kept below the tolerance:

- Discretisation (the largest): Hertz h = a/4 under the contact (a = sqrt(R d) the contact radius),
  uniform over [0, a] laterally and over the top a, then growing by 3x per cell; layer h = 0.5 mm (a/2 and
  a/3) over the top 2 mm, growing by 2x. P2 with one volumetric quadrature point per tet does not lock:
  at nu = 0.49 it is slightly too soft (-1.9 %) rather than far too stiff, which is what the nu = 0.49 case
  shows (P1 tets are 30-80 % too stiff there, see scripts/fem_error_vs_runtime.py).
- Finite domain (Hertz): the quarter block is 100 a wide and 100 a deep, roller bottom (u_z = 0), free
  sides. A layer of depth L over a rigid base stiffens the contact by about 0.6 a / L, i.e. ~0.6 %.
- Faceting: icosphere with 7 subdivisions of a R = 10 mm sphere (edges ~0.1 mm): the facets lie at most
  1.3e-4 mm inside the sphere, 0.1 % of the depth (-0.2 % force); the contact normal is the facet normal.
- Penalty penetration: contact stiffness 5000 N/mm^3 (instead of the size-based default, which for these
  strongly graded meshes is only ~300), so p/k <= 5e-5 mm, <= 0.05 % of the depth.
- Sphere against paraboloid and the small-strain assumption of both formulas: d/R = 0.01 (Hertz) and
  <= 0.025 (layer); the exact sphere solution (Sneddon) differs from Hertz by -0.1 d/R, i.e. -0.1 %.
- Newton tolerance 1e-6 mm: the solver's step criterion (a line-search-damped step below the tolerance
  counts as converged) can stop early with a stiff contact: with this set-up the Hertz force came out
  +12.7 % (nu 0.45, tol 1e-4) and +43 % (nu 0.49, tol 1e-3) off, so these tests converge tightly.

Dimitriadis et al. (2002) is itself a series fit for chi = sqrt(R d)/h <= 1; at chi = 0.2 and 0.32 it is
accurate to about 1 %.
"""

import numpy as np
import pytest
import trimesh

from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter, SolverSettings
from transtac_sim.physics.analytic import bonded_layer_force, hertz_force
from transtac_sim.physics.box_mesh import box_tet_mesh, graded_coordinates

RADIUS = 10.0
SETTINGS = SolverSettings(degree=2, newton_tol_mm=1e-6, contact_stiffness=5000.0)


def quarter_sphere_forces(poisson, depths, size, thickness, h_fine, fine, growth, bonded):
    """Total force 4 x (-F_z) of a frictionless sphere pressed to each depth in turn at the corner x = y = 0."""
    xs = graded_coordinates(0.0, size, h_fine, 0.0, fine, growth)
    zs = graded_coordinates(0.0, thickness, h_fine, thickness - fine, thickness, growth)
    V, T = box_tet_mesh(xs, xs, zs)
    bottom = V[:, 2] < 1e-9
    fixed = np.stack([V[:, 0] < 1e-9, V[:, 1] < 1e-9, bottom], axis=1)
    if bonded:
        fixed |= bottom[:, None]
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=7, radius=RADIUS))
    solver = QuasiStaticSolver(V, T, ElasticMaterial(1.0, poisson), [sphere], SETTINGS, fixed=fixed)
    pose = np.eye(4)
    pose[2, 3] = thickness + RADIUS + 1e-3
    solver.start([pose])
    forces, records = [], []
    for depth in depths:
        pose = pose.copy()
        pose[2, 3] = thickness + RADIUS - depth
        res = solver.solve_frame([pose])
        assert res.record.converged and res.record.min_det_f > 0
        forces.append(-4.0 * res.forces_n[0, 2])
        records.append(res.record)
    return np.array(forces), records


@pytest.mark.slow
@pytest.mark.parametrize("poisson", [0.3, 0.45, 0.49])
def test_hertz_half_space(poisson):
    depth = 0.1  # contact radius a = 1 mm, h = a/4, block 100 a wide and deep
    forces, records = quarter_sphere_forces(poisson, [depth], 100.0, 100.0, 0.25, 1.0, 3.0, bonded=False)
    expected = hertz_force(1.0, poisson, RADIUS, depth)
    print(f"Hertz nu {poisson}: F {forces[0]:.5f} N, expected {expected:.5f} N ({100 * (forces[0] / expected - 1):+.2f} %)")
    assert abs(forces[0] / expected - 1.0) < 0.03, (forces, expected, records)


@pytest.mark.slow
def test_bonded_thin_layer():
    """The real gel: 5 mm, bonded, nearly incompressible; force against depth at two depths."""
    depths, thickness, poisson = [0.1, 0.25], 5.0, 0.49  # a = 1 and 1.6 mm, chi = 0.2 and 0.32
    forces, records = quarter_sphere_forces(poisson, depths, 15.0, thickness, 0.5, 2.0, 2.0, bonded=True)
    expected = bonded_layer_force(1.0, poisson, RADIUS, np.array(depths), thickness)
    print(f"bonded layer: F {forces} N, expected {expected} N ({100 * (forces / expected - 1)} %)")
    # the layer is much stiffer than the half-space here (about +25 % and +40 %): the test tells them apart
    assert np.all(forces > 1.15 * hertz_force(1.0, poisson, RADIUS, np.array(depths)))
    assert np.all(np.abs(forces / expected - 1.0) < 0.05), (forces, expected, records)
