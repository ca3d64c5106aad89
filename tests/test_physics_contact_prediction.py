"""The Newton step's contact prediction (physics/contact_prediction.py): the predicted gap against a flat face, and a
release that takes the predicted contact and ends where it ends without it."""

import numpy as np
import trimesh
import warp as wp

from transtac_sim.physics import ElasticMaterial, QuasiStaticSolver, RigidIndenter
from transtac_sim.physics.box_mesh import box_tet_mesh, gel_block
from transtac_sim.physics.contact_prediction import PREDICT_DEPTH_MM, ContactPrediction


def _lift(z):
    P = np.eye(4)
    P[2, 3] = z
    return P


def _uniform_step(solver, dz_mm: float) -> wp.array:
    values = np.zeros((len(solver.u.dof_values), 3))
    values[:, 2] = dz_mm
    return wp.array(values, dtype=wp.vec3d, device=solver.device)


def test_predicted_gap_under_a_flat_plate_is_the_gap():
    """A plate 0.1 mm above a block's top face: a step lifting the face 0.3 mm puts every top contact point 0.2 mm into
    it, so each is predicted with k, the push-out normal -z and the signed gap -0.1 mm at u (exact on a flat face); a
    step of 0.12 mm (0.02 mm deep) predicts nothing, and neither does a point already in contact at u."""
    V, T = box_tet_mesh(np.linspace(0, 4, 3), np.linspace(0, 4, 3), np.linspace(0, 2, 3))
    sides_and_bottom = (np.minimum(V[:, 0], V[:, 1]) < 1e-9) | (np.maximum(V[:, 0], V[:, 1]) > 4.0 - 1e-9) | (
        V[:, 2] < 1e-9)  # fixed: only the top face's sides can touch
    plate = RigidIndenter.from_trimesh("plate", trimesh.creation.box(extents=(40.0, 40.0, 2.0)))
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [plate], fixed=sides_and_bottom)
    P = _lift(2.0 + 1.0 + 0.1)
    solver.start([P])
    ind = solver._indenter_struct([P], [P])
    assert solver._predicted_points(ind, _uniform_step(solver, 0.3))
    pred = solver._prediction.pred
    on_top = solver._q_contact.total_point_count()
    k, gap, normal = pred.stiffness.numpy(), pred.gap.numpy(), pred.normal.numpy()
    assert np.count_nonzero(k) == on_top and np.all((k == 0.0) | (k == float(ind.stiffness)))
    np.testing.assert_allclose(gap[k > 0], -0.1, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(normal[k > 0], [[0.0, 0.0, -1.0]] * on_top, atol=1e-12)
    assert not solver._predicted_points(ind, _uniform_step(solver, 0.1 + 0.8 * PREDICT_DEPTH_MM))
    solver.u.dof_values.assign(_uniform_step(solver, 0.15))  # in contact at u, 0.05 mm deep
    assert not solver._predicted_points(ind, _uniform_step(solver, 0.3))


def _press_and_release(predict: bool, monkeypatch):
    if not predict:
        monkeypatch.setattr(ContactPrediction, "_predict_contact", lambda self, *args: None)
    V, T = gel_block(6.0, 6.0, 2.0, h_fine=0.6, fine_half_width=1.2, growth=2.0)
    sphere = RigidIndenter.from_trimesh("sphere", trimesh.creation.icosphere(subdivisions=3, radius=2.0))
    solver = QuasiStaticSolver(V, T, ElasticMaterial(0.5, 0.45), [sphere])
    solver.start([_lift(4.0 + 1e-3)])
    presses = [solver.solve_frame([_lift(4.0 - d)]) for d in (0.3, 0.6)]
    return presses, solver.solve_frame([_lift(4.0 - 0.1)])


def test_release_takes_the_predicted_contact_and_ends_where_it_ends_without(monkeypatch):
    """A sphere released from 0.6 to 0.1 mm: the gel springs back into it, and Newton's full steps overshoot into the
    sphere. With the prediction the release takes 5 Newton iterations against 15 (measured; this checks at most half),
    to the same state; the presses predict nothing (only steps that lift an indenter do)."""
    presses, released = _press_and_release(True, monkeypatch)
    assert all(p.record.predicted_contacts == 0 for p in presses)
    assert released.record.converged and released.record.predicted_contacts >= 1, released.record
    _, plain = _press_and_release(False, monkeypatch)
    assert plain.record.converged and plain.record.predicted_contacts == 0
    assert released.record.iterations <= plain.record.iterations // 2, (released.record, plain.record)
    np.testing.assert_allclose(released.forces_n, plain.forces_n, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(released.displacement_mm, plain.displacement_mm, rtol=0.0, atol=1e-6)
