"""The speckle texture: fixed to the body (a function of the mesh's own vertices), with full contrast
between its floor and the indenter's colour, the same for the same seed."""

from __future__ import annotations

import numpy as np
import trimesh

from transtac_sim.indenters.texture import speckle_albedo
from transtac_sim.rendering.illumination import lambertian_radiance


def test_speckle_is_fixed_to_the_body_and_has_contrast():
    v = trimesh.creation.icosphere(subdivisions=4, radius=4.0).vertices
    rgb = (0.8, 0.6, 0.4)
    a = speckle_albedo(v, rgb, scale_mm=0.8, seed=1)
    assert a.shape == (len(v), 3)
    assert np.allclose(a / np.asarray(rgb), (a / np.asarray(rgb))[:, :1])  # a grey pattern times the colour
    level = a[:, 0] / rgb[0]
    assert level.min() >= 0.15 - 1e-12 and level.max() <= 1.0 + 1e-12
    assert np.percentile(level, 95) - np.percentile(level, 5) > 0.7
    assert np.array_equal(a, speckle_albedo(v, rgb, 0.8, seed=1))
    assert not np.allclose(a, speckle_albedo(v, rgb, 0.8, seed=2))
    # neighbouring vertices (0.3 mm apart) are alike, features of the requested size differ
    d = np.linalg.norm(v[:, None] - v[None, :200], axis=2)
    close = (d > 0) & (d < 0.35)
    far = d > 3.0
    diff = np.abs(level[:, None] - level[None, :200])
    assert diff[close].mean() < 0.5 * diff[far].mean()


def test_lambertian_radiance_takes_a_colour_per_point():
    e = np.array([1.0, 2.0])
    per_point = lambertian_radiance(e, np.array([[0.5, 0.5, 0.5], [1.0, 0.0, 0.0]]))
    assert np.allclose(per_point, [[0.5 / np.pi] * 3, [2.0 / np.pi, 0.0, 0.0]])
    assert np.allclose(lambertian_radiance(e, (1.0, 1.0, 1.0)), e[:, None] / np.pi * np.ones(3))
