"""The camera geometry: Mitsuba's sensor reproduces an OpenCV K exactly (a rendered point lands where
K projects it), the distortion remap lands it where cv2.projectPoints does, undistortion round-trips,
and the sensor effects (noise, vignetting, gain, quantisation) behave."""

from __future__ import annotations

import numpy as np
import pytest

from transtac_sim.camera.model import CameraEffects, CameraModel, project, unproject
from transtac_sim.rendering.inputs import CameraSpec
from transtac_sim.rendering.mitsuba_env import select_variant
from transtac_sim.rendering.sensors import perspective_sensor

mi = select_variant()


def _rot(axis, deg):
    import cv2

    return cv2.Rodrigues(np.radians(deg) * np.asarray(axis, float))[0]


def _render_point(K, size, R, T, p_world, radius=0.15, spp=1024):
    """Near noise-free render of a tiny emitting sphere at ``p_world`` (box filter: exact pixel integrals)."""
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                          "s": {"type": "sphere", "center": list(map(float, p_world)), "radius": radius,
                                "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
    img = np.array(mi.render(scene, sensor=perspective_sensor(mi, K, size, R, T, spp, sampler="stratified"), spp=spp))[..., 0]
    return img


def _centroid(img):
    v, u = np.mgrid[: img.shape[0], : img.shape[1]]
    return np.array([(img * u).sum(), (img * v).sum()]) / img.sum()


@pytest.mark.parametrize("pose", ["identity", "rotated"])
def test_rendered_point_lands_on_K_projection(pose):
    K = np.array([[50.0, 0, 37.3], [0, 50.0, 20.6], [0, 0, 1]])  # principal point well off centre
    size = (64, 48)
    R, T = (np.eye(3), np.zeros(3)) if pose == "identity" else (_rot([0.2, -1, 0.3], 12.0), np.array([-3.0, 1.0, 0.5]))
    for p_cam in ([0.0, 0.0, 10.0], [-4.0, 2.5, 10.0], [5.0, -3.0, 12.0]):
        p_world = R.T @ (np.asarray(p_cam) - T)
        uv = (K @ p_cam)[:2] / p_cam[2]
        c = _centroid(_render_point(K, size, R, T, p_world))
        assert np.abs(c - uv).max() < 0.02, (p_cam, c, uv)


def test_distortion_remap_lands_on_projectPoints():
    spec = CameraSpec(K=np.array([[40.0, 0, 31.0], [0, 42.0, 25.0], [0, 0, 1]]), dist=np.array([-0.25, 0.06, 0.002, -0.001, 0.0]),
                      size=(64, 48))
    cam = CameraModel(spec, CameraEffects(noise=False, quantize=False))
    assert cam.render_size[0] > 64  # barrel distortion: the pinhole render must be wider
    for p in ([0.0, 0.0, 10.0], [-9.0, 6.0, 10.0], [10.0, -7.0, 10.0]):
        pin = _render_point(cam.render_K, cam.render_size, np.eye(3), np.zeros(3), p, radius=0.2)
        rec = cam.to_recorded(pin[..., None])[..., 0]
        uv = project(spec, np.array([p]))[0]
        assert np.abs(_centroid(rec) - uv).max() < 0.05, (p, _centroid(rec), uv)


@pytest.mark.parametrize("model,dist", [("pinhole", [-0.12, 0.02, 0.001, -0.002, 0.0]), ("fisheye", [0.05, -0.01, 0.002, 0.0])])
def test_unproject_inverts_project(model, dist):
    spec = CameraSpec(K=np.array([[270.0, 0, 321.0], [0, 268.0, 238.0], [0, 0, 1]]), dist=np.array(dist), size=(640, 480),
                      model=model)
    uv = np.random.default_rng(0).uniform([0, 0], [639, 479], (500, 2))
    xy = unproject(spec, uv)
    back = project(spec, np.column_stack([xy, np.ones(len(xy))]))
    assert np.abs(back - uv).max() < 1e-6


def test_non_invertible_distortion_is_refused():
    spec = CameraSpec(K=np.array([[270.0, 0, 319.5], [0, 270.0, 239.5], [0, 0, 1]]), dist=np.array([-0.3, 0.1, 0, 0, -0.02]),
                      size=(640, 480))
    with pytest.raises(ValueError, match="not invertible"):
        CameraModel(spec)


def test_no_distortion_renders_at_K_directly():
    spec = CameraSpec(K=np.array([[50.0, 0, 30.0], [0, 50.0, 20.0], [0, 0, 1]]), dist=np.zeros(5), size=(64, 48))
    cam = CameraModel(spec)
    assert cam.render_size == (64, 48) and np.array_equal(cam.render_K, spec.K)
    x = np.random.default_rng(1).random((48, 64, 3)).astype(np.float32)
    assert cam.to_recorded(x) is not None and np.array_equal(cam.to_recorded(x), x)


def test_sensor_effects():
    spec = CameraSpec(K=np.array([[30.0, 0, 31.5], [0, 30.0, 23.5], [0, 0, 1]]), dist=np.zeros(5), size=(64, 48))
    flat = np.full((48, 64, 3), 0.5, np.float32)
    ideal = CameraModel(spec, CameraEffects(noise=False, quantize=False)).expose(flat)
    assert np.allclose(ideal, 0.5)
    noisy = CameraModel(spec, CameraEffects(full_well_electrons=1000.0))
    a, b, c = noisy.expose(flat, 3), noisy.expose(flat, 3), noisy.expose(flat, 4)
    assert a.dtype == np.uint8 and np.array_equal(a, b) and not np.array_equal(a, c)
    # Poisson-Gaussian: variance of the value = x / full_well + (read / full_well)^2
    expected_std = np.sqrt(0.5 / 1000 + (4 / 1000) ** 2) * 255
    assert abs(a.astype(float).std() - expected_std) < 0.15 * expected_std
    vig = CameraModel(spec, CameraEffects(noise=False, quantize=False, vignetting=1.0)).expose(flat)[..., 0]
    assert vig[24, 32] > 0.49 and vig[0, 0] < 0.8 * vig[24, 32]
    gain = CameraModel(spec, CameraEffects(noise=False, gain=3.0)).expose(flat)
    assert (gain == 255).all()
