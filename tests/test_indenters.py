"""Indenter meshes: the parametric library is watertight with the right volume; bad meshes are refused
(or repaired, where the repair is documented) with a message naming the file."""

from __future__ import annotations

import re
from math import pi
from pathlib import Path

import numpy as np
import pytest
import trimesh
from conftest import REPO

from transtac_sim.indenters.library import LIBRARY, SECTIONS, polygon_volume_ratio
from transtac_sim.indenters.loading import IndenterMeshError, check_and_repair, load_indenter_mesh


@pytest.mark.parametrize("name", sorted(LIBRARY))
def test_library_stl_is_watertight_with_the_right_volume(name: str):
    spec = LIBRARY[name]
    loaded = load_indenter_mesh(REPO / "scenes" / "indenters" / f"{name}.stl", "mm")
    m = loaded.mesh
    assert m.is_watertight and m.is_winding_consistent and len(m.split()) == 1
    # A triangulated circle of SECTIONS segments holds polygon_volume_ratio() of the disc's area; the
    # icosphere (5120 faces) loses 0.2 %. Flat-faced shapes are exact.
    ratio = m.volume / spec.volume_mm3
    assert polygon_volume_ratio(SECTIONS) - 1e-4 <= ratio <= 1 + 1e-9 or name == "sphere_r4", ratio
    assert ratio == pytest.approx(1.0, abs=2.5e-3)
    # The committed STL is what the generator builds.
    assert m.volume == pytest.approx(spec.build().volume, rel=1e-6)
    # The contact feature points down: the lowest point is at the bottom of the bounding box.
    assert m.bounds[0][2] == pytest.approx(-m.extents[2] / 2, abs=1e-6)


def test_polygon_volume_ratio_is_exact():
    assert polygon_volume_ratio(4) == pytest.approx(2 / pi)  # a square inscribed in the unit circle


def _write(tmp_path: Path, mesh: trimesh.Trimesh, name: str = "m.stl") -> Path:
    p = tmp_path / name
    mesh.export(p)
    return p


def test_units_are_converted_to_mm(tmp_path: Path):
    box_m = trimesh.creation.box((0.01, 0.02, 0.005))  # metres
    m = load_indenter_mesh(_write(tmp_path, box_m), "m").mesh
    assert m.extents == pytest.approx([10, 20, 5]) and m.volume == pytest.approx(1000.0)
    inch = load_indenter_mesh(_write(tmp_path, trimesh.creation.box((1, 1, 1))), "inch").mesh
    assert inch.volume == pytest.approx(25.4**3)


def test_absurd_size_suggests_the_unit(tmp_path: Path):
    p = _write(tmp_path, trimesh.creation.box((0.01, 0.02, 0.005)))  # metres declared as mm
    with pytest.raises(IndenterMeshError, match=r"largest extent is 0.02 mm .*did you mean units = 'm'"):
        load_indenter_mesh(p, "mm")


def test_empty_file(tmp_path: Path):
    p = tmp_path / "empty.stl"
    p.write_bytes(b"")
    with pytest.raises(IndenterMeshError, match=str(p)):
        load_indenter_mesh(p, "mm")


def test_cut_short_or_text_file_says_so(tmp_path: Path):
    """A binary STL cut short (a failed copy) or a text file named .stl: no faces read, and the message says why."""
    whole = (REPO / "scenes/indenters/sphere_r4.stl").read_bytes()
    for name, data in (("cut.stl", whole[:300]), ("notes.stl", b"these are my notes, not a mesh\n")):
        p = tmp_path / name
        p.write_bytes(data)
        with pytest.raises(IndenterMeshError, match=re.escape(f"{p}: no faces could be read: the file is empty, cut "
                                                              "short, or not a mesh file")):
            load_indenter_mesh(p, "mm")


def test_open_mesh_is_refused(tmp_path: Path):
    box = trimesh.creation.box((5, 5, 5))
    box.update_faces(np.arange(len(box.faces)) != 0)
    with pytest.raises(IndenterMeshError, match=r"not watertight .* 1 open edges|not watertight"):
        check_and_repair(box, "open.stl")


def test_several_bodies_are_refused(tmp_path: Path):
    two = trimesh.util.concatenate([trimesh.creation.box((2, 2, 2)),
                                    trimesh.creation.box((2, 2, 2)).apply_translation((5, 0, 0))])
    with pytest.raises(IndenterMeshError, match="2 separate bodies"):
        load_indenter_mesh(_write(tmp_path, two), "mm")


def test_degenerate_faces_and_inverted_winding_are_repaired():
    box = trimesh.creation.box((4, 4, 4))
    v = box.vertices
    faces = np.vstack([box.faces[:, ::-1], [[0, 0, 1]], [[0, 1, 1]]])  # inside-out plus two degenerate faces
    loaded = check_and_repair(trimesh.Trimesh(v, faces, process=False), "bad.stl")
    assert loaded.mesh.volume == pytest.approx(64.0)
    assert any("degenerate" in r for r in loaded.repairs) and any("outward" in r for r in loaded.repairs)
