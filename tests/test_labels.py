"""Exact marker labels without rendering: the refracted path against an independent forward Snell trace,
and the visibility rules (outside the image, path leaving through a side face, hidden behind a marker)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from transtac_sim.labels.markers import frame_labels, planar_stack
from transtac_sim.labels.refraction import refracted_paths, solve_exit_sine
from transtac_sim.rendering import demo_scene
from transtac_sim.rendering.inputs import FrameState


def test_exit_sine_of_a_single_layer_is_geometric():
    rho = np.array([0.0, 1.0, 5.0, 40.0])
    s = solve_exit_sine(rho, [(np.full(4, 10.0), 1.0)])
    assert np.allclose(s, np.sin(np.arctan(rho / 10.0)), atol=1e-12)


def _snell(d, n1, n2):
    """Refract unit direction ``d`` (going +z) through a plane z = const from index n1 into n2."""
    t = d[:2] * n1 / n2
    return np.array([t[0], t[1], np.sqrt(1 - t @ t)])


def test_refracted_path_reaches_the_point():
    """Trace each label path forward from the camera with Snell's law at both planes: it must pass
    through the point."""
    scene = demo_scene.sensor_scene()
    stack = planar_stack(scene)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-15, 15, 30), rng.uniform(-11, 11, 30), rng.uniform(17.2, 21.9, 30)])
    for cam in scene.cameras.values():
        C = cam.centre
        paths = refracted_paths(stack, C, pts)
        for p, d in zip(pts, paths.directions_left, strict=True):
            x = C + d * (stack.z_back - C[2]) / d[2]
            d = _snell(d, 1.0, stack.n_backing)
            x = x + d * (stack.z_bond - stack.z_back) / d[2]
            d = _snell(d, stack.n_backing, stack.n_gel)
            x = x + d * (p[2] - stack.z_bond) / d[2]
            assert np.linalg.norm(x - p) < 1e-9


def test_visibility_rules():
    scene = demo_scene.sensor_scene(markers=np.array([[0.0, 0.0, 21.5], [0.0, 0.0, 19.0], [15.8, 0.0, 21.5],
                                                       [-15.5, 11.5, 21.5]]))
    c = scene.markers.centres
    # put marker 1 on the left camera's path of marker 0
    q = refracted_paths(planar_stack(scene), scene.cameras["left"].centre, c[:1]).at_bond[0]
    c[1] = c[0] + 0.6 * (q - c[0])
    far = dataclasses.replace(scene.cameras["right"], T=np.array([-40.0, 0.0, 0.0]))  # camera beyond the gel's side
    narrow = dataclasses.replace(scene.cameras["left"], K=scene.cameras["left"].K * [[2, 1, 1], [1, 2, 1], [1, 1, 1]])
    labels = frame_labels(scene, None, {"left": scene.cameras["left"], "far": far, "narrow": narrow})
    assert list(labels["left"].visible) == [False, True, True, True]
    assert not labels["far"].visible[2]  # its path to x = 40 leaves the gel through the face x = 16
    assert labels["narrow"].visible[:2].tolist() == [False, True] and not labels["narrow"].visible[3]  # outside
    lab = labels["left"]
    assert np.all(lab.bbox[:, :2] <= lab.uv) and np.all(lab.uv <= lab.bbox[:, 2:])
    json.dumps(lab.as_views())


def test_deformed_surface_hides_a_marker_below_a_fold():
    """A marker whose path towards the camera crosses the (deformed) contact face is not visible."""
    scene = demo_scene.sensor_scene(markers=np.array([[12.0, 0.0, 21.5]]))
    v = scene.gel.vertices.copy()
    top = np.isclose(v[:, 2], 22.0)
    # a deep narrow trench at x in [10.5, 12]: the surface dips to z = 18 between the marker and the camera
    v[top & (v[:, 0] > 10.6) & (v[:, 0] < 11.6), 2] = 18.0
    flat, folded = (frame_labels(scene, FrameState(gel_vertices=g), {"left": scene.cameras["left"]})["left"]
                    for g in (scene.gel.vertices, v))
    assert flat.visible[0] and not folded.visible[0]
