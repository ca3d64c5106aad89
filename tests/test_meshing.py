"""Gel meshing: exact marker embedding, affine fields followed exactly, quality, and the cache."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REPO

from transtac_sim.meshing import mesh_gel
from transtac_sim.meshing.embedding import embed_points
from transtac_sim.meshing.gel_mesh import signed_volumes
from transtac_sim.meshing.quality import mesh_quality
from transtac_sim.scene_setup import load_setup


@pytest.fixture(scope="module")
def meshed():
    setup = load_setup(REPO / "scenes" / "press_slide.toml")
    return setup, mesh_gel(setup, use_cache=False)


def test_mesh_fills_the_gel_with_positive_tets(meshed):
    setup, m = meshed
    v, t = m.mesh.vertices_mm, m.mesh.tets
    w, h, th = setup.sensor.gel_size_mm
    assert np.allclose(v.min(axis=0), [-w / 2, -h / 2, 0]) and np.allclose(v.max(axis=0), [w / 2, h / 2, th])
    vol = signed_volumes(v, t)
    assert vol.min() > 0 and vol.sum() == pytest.approx(w * h * th, rel=1e-9)
    assert len(m.mesh.bonded_vertices) > 20  # the bonded face is exactly z = 0
    assert m.quality.min_dihedral_deg > 5.0


def test_refined_under_the_contact_region(meshed):
    _, m = meshed
    v, t = m.mesh.vertices_mm, m.mesh.tets
    c = v[t].mean(axis=1)
    edge = np.linalg.norm(v[t[:, 0]] - v[t[:, 1]], axis=1)
    x0, y0, x1, y1 = m.contact_region
    inside = (c[:, 0] > x0) & (c[:, 0] < x1) & (c[:, 1] > y0) & (c[:, 1] < y1)
    assert np.median(edge[inside]) < 0.7 * np.median(edge[~inside])


def test_embedding_reproduces_marker_positions(meshed):
    setup, m = meshed
    p = m.markers.interpolate(m.mesh.tets, m.mesh.vertices_mm)
    assert np.abs(p - setup.sensor.markers_rest_gel_mm).max() < 1e-9
    assert m.markers.barycentric.min() >= -1e-9
    assert np.allclose(m.markers.barycentric.sum(axis=1), 1.0)


def test_embedded_markers_follow_an_affine_field_exactly(meshed):
    setup, m = meshed
    rng = np.random.default_rng(3)
    A, b = np.eye(3) + 0.1 * rng.standard_normal((3, 3)), rng.standard_normal(3)
    displaced = m.mesh.vertices_mm @ A.T + b
    p = m.markers.interpolate(m.mesh.tets, displaced)
    assert np.abs(p - (setup.sensor.markers_rest_gel_mm @ A.T + b)).max() < 1e-9


def test_embedding_refuses_points_outside():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    t = np.array([[0, 1, 2, 3]])
    e = embed_points(v, t, [[0.1, 0.2, 0.3]])
    assert np.allclose(e.barycentric, [[0.4, 0.1, 0.2, 0.3]])
    with pytest.raises(ValueError, match="outside the mesh"):
        embed_points(v, t, [[1.0, 1.0, 1.0]])


def test_quality_of_a_regular_tet():
    v = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1.0]])
    q = mesh_quality(v, np.array([[0, 1, 2, 3]]))
    assert q.min_dihedral_deg == pytest.approx(np.degrees(np.arccos(1 / 3)))
    assert q.max_aspect_ratio == pytest.approx(1.0)


def test_cache_is_hit_on_the_second_call():
    setup = load_setup(REPO / "scenes" / "press_slide.toml")
    first = mesh_gel(setup)
    second = mesh_gel(setup)
    assert not first.cache_hit and second.cache_hit and first.cache_key == second.cache_key
    assert np.array_equal(first.mesh.tets, second.mesh.tets)
    assert np.array_equal(first.mesh.vertices_mm, second.mesh.vertices_mm)


def test_cache_key_follows_placement_not_appearance_or_last_bits():
    """The key hashes the configured inputs of the contact region (a cache made on another machine, whose BLAS
    rounds the posed indenter's last bits differently, is found), not colour or friction; a move changes it."""
    import dataclasses

    from transtac_sim.meshing import cache, region_inputs

    setup = load_setup(REPO / "scenes" / "press_slide.toml")

    def with_indenter(**update):
        ind = setup.indenters[0]
        placed = dataclasses.replace(ind, config=ind.config.model_copy(update=update))
        return dataclasses.replace(setup, indenters=type(setup.indenters)([placed]))

    def key(s):
        return cache.mesh_key(region=region_inputs(s))

    noisy = dataclasses.replace(setup.indenters[0], start_pose=setup.indenters[0].start_pose * (1 + 1e-15))
    assert key(dataclasses.replace(setup, indenters=type(setup.indenters)([noisy]))) == key(setup)
    assert key(with_indenter(color_rgb=(0.1, 0.2, 0.3), friction=0.9, texture="speckle")) == key(setup)
    x, y = setup.indenters[0].config.start_xy_mm
    assert key(with_indenter(start_xy_mm=(x + 0.5, y))) != key(setup)
