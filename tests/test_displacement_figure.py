"""displacement.png cuts its section through the contact, not through the indenter's mesh origin.

A synthetic frame: the 32 x 24 x 5 mm gel on a 0.5 mm grid, a sphere (R 2 mm) pressed 0.3 mm in at
x = 3, y = -4 mm, the gel's top surface following the sphere where it is pressed; the sphere's STL origin
lies 24 mm from its centre (a CAD file), so its pose's translation is at y = 20 mm, off the gel."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from transtac_sim.meshing.gel_mesh import GelMesh
from transtac_sim.physics.box_mesh import box_tet_mesh
from transtac_sim.reports.displacement_figure import (
    IMAGE_SIZE_PX,
    IndenterView,
    save_displacement_figure,
    section_y,
)

W, H, T = 32.0, 24.0, 5.0
CENTRE = np.array([3.0, -4.0])
RADIUS, DEPTH = 2.0, 0.3


def _frame(pressed: bool):
    V, tets = box_tet_mesh(np.linspace(-W / 2, W / 2, 65), np.linspace(-H / 2, H / 2, 49), np.linspace(0, T, 3))
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=RADIUS)
    local = sphere.vertices + [0.0, -24.0, 0.0]  # the file's origin 24 mm from the body
    pose = np.eye(4)
    pose[:3, 3] = [CENTRE[0], CENTRE[1] + 24.0, T + RADIUS - (DEPTH if pressed else -0.5)]
    u = np.zeros_like(V)
    if pressed:  # the top surface follows the sphere's underside where the sphere is below z = T
        r2 = ((V[:, :2] - CENTRE) ** 2).sum(axis=1)
        under = (V[:, 2] == T) & (r2 < RADIUS**2)
        z_sphere = pose[2, 3] - np.sqrt(RADIUS**2 - r2[under])
        u[under, 2] = np.minimum(z_sphere - T, 0.0)
    force = np.array([0.0, 0.0, -0.2 if pressed else 0.0])
    return V, tets, u, IndenterView("cad", local, np.asarray(sphere.faces), pose, force)


def test_section_goes_through_the_contact_not_the_mesh_origin():
    V, tets, u, ind = _frame(pressed=True)
    top = GelMesh(V, tets).boundary_faces()
    surface = (V + u)[np.unique(top)]
    y0, through = section_y([ind], surface)
    assert abs(y0 - CENTRE[1]) < 0.05 and through == "the contact", y0  # the contact patch is symmetric about y = -4 on this grid
    assert abs(ind.pose[1, 3] - CENTRE[1]) == 24.0  # where the section used to be: off the gel


def test_without_contact_the_section_goes_through_the_footprint():
    V, tets, u, ind = _frame(pressed=False)
    surface = (V + u)[np.unique(GelMesh(V, tets).boundary_faces())]
    y0, through = section_y([ind], surface)
    assert abs(y0 - CENTRE[1]) < 1e-9 and through == "cad's footprint (no contact)"


def test_figure_cuts_the_gel_where_the_contact_is(tmp_path: Path, monkeypatch):
    import transtac_sim.reports.displacement_figure as fig

    cuts, slice_tets = [], fig._slice_tets

    def recording_slice(x, tets, values, y0):
        section = slice_tets(x, tets, values, y0)
        cuts.append((y0, section[2]))
        return section

    monkeypatch.setattr(fig, "_slice_tets", recording_slice)
    V, tets, u, ind = _frame(pressed=True)
    markers = np.array([[0.0, 0.0, 4.4], [3.0, -4.0, 4.4]])
    path = save_displacement_figure(
        tmp_path / "d.png", title="off origin", frame=0, gel_size_mm=(W, H, T), markers_rest_mm=markers,
        markers_mm=markers + [0.0, 0.0, -0.1], rest_vertices_mm=V, vertices_mm=V + u, tets=tets,
        boundary_faces=GelMesh(V, tets).boundary_faces(), indenters=[ind])
    b = path.read_bytes()
    assert (int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")) == IMAGE_SIZE_PX
    (y0, triangles), = cuts
    assert abs(y0 - CENTRE[1]) < 0.05 and len(triangles) > 0  # a section of the gel, through the contact
