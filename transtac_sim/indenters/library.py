"""Parametric indenters: the shapes of ``scenes/indenters/`` with their exact volumes.

Each shape is built in its own frame, mm: the contact feature points to -z (indenters press toward -z
in the gel frame) and the origin is the centre of the bounding box. ``volume_mm3`` is the volume of the
ideal (curved) solid; a triangulated mesh with ``sections`` segments per circle is slightly smaller.
Booleans (studs, rims, pockets) use the manifold engine, so every result is one watertight body.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from math import atan, cos, pi, sin

import numpy as np
import trimesh

SECTIONS = 96  # segments per full circle


def _centred(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    return mesh


def _union(*meshes: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.boolean.union(list(meshes), engine="manifold")


def sphere(radius_mm: float = 4.0) -> trimesh.Trimesh:
    return _centred(trimesh.creation.icosphere(subdivisions=4, radius=radius_mm))


def cylinder(radius_mm: float = 3.0, length_mm: float = 16.0) -> trimesh.Trimesh:
    """A roller: axis along y, so it rolls along x."""
    m = trimesh.creation.cylinder(radius=radius_mm, height=length_mm, sections=SECTIONS)
    m.apply_transform(trimesh.transformations.rotation_matrix(pi / 2, [1, 0, 0]))
    return _centred(m)


def flat_punch(radius_mm: float = 3.0, height_mm: float = 6.0) -> trimesh.Trimesh:
    """A vertical cylinder pressing with its flat circular face."""
    return _centred(trimesh.creation.cylinder(radius=radius_mm, height=height_mm, sections=SECTIONS))


def cube_edge(side_mm: float = 6.0) -> trimesh.Trimesh:
    """A cube turned 45 degrees about y: a sharp edge along y points down."""
    m = trimesh.creation.box((side_mm, side_mm, side_mm))
    m.apply_transform(trimesh.transformations.rotation_matrix(pi / 4, [0, 1, 0]))
    return _centred(m)


def cone(radius_mm: float = 4.0, height_mm: float = 6.0, tip_radius_mm: float = 0.5) -> trimesh.Trimesh:
    """A cone (base radius, apex height) with its tip down, the tip rounded by a sphere of ``tip_radius_mm``
    tangent to the sides (a printed or machined tip is never sharper; a sharp one inverts the elements
    under it). The solid is shorter than ``height_mm`` by tip_radius / sin(half-angle) - tip_radius."""
    half_angle = atan(radius_mm / height_mm)
    t = np.linspace(0.0, 2.0 * pi, SECTIONS, endpoint=False)
    base = np.column_stack([radius_mm * np.cos(t), radius_mm * np.sin(t), np.full(SECTIONS, height_mm)])
    tip = trimesh.creation.icosphere(subdivisions=4, radius=tip_radius_mm).vertices
    tip[:, 2] += tip_radius_mm / sin(half_angle)  # (sharp) apex at the origin, base at z = height_mm: tip down
    return _centred(trimesh.convex.convex_hull(np.vstack([base, tip])))


def _rounded_cone_volume(radius_mm: float, height_mm: float, tip_radius_mm: float) -> float:
    """The cone up to the circle where the tip sphere touches it, plus the spherical cap below that circle."""
    a, r = atan(radius_mm / height_mm), tip_radius_mm
    z_t, rho_t, h_cap = r * cos(a) ** 2 / sin(a), r * cos(a), r * (1.0 - sin(a))
    return pi / 3 * (height_mm * radius_mm**2 - z_t * rho_t**2) + pi * h_cap**2 * (3.0 * r - h_cap) / 3


def coin(radius_mm: float = 11.6, thickness_mm: float = 1.6, rim_width_mm: float = 1.0, rim_height_mm: float = 0.4) -> trimesh.Trimesh:
    """A coin (1-euro size) lying flat, its raised rim down."""
    disc = trimesh.creation.cylinder(radius=radius_mm, height=thickness_mm, sections=SECTIONS)
    ring = trimesh.creation.annulus(r_min=radius_mm - rim_width_mm, r_max=radius_mm, height=rim_height_mm, sections=SECTIONS)
    ring.apply_translation([0, 0, -(thickness_mm + rim_height_mm) / 2])
    return _centred(_union(disc, ring))


def studded_brick(studs_x: int = 2, studs_y: int = 2, pitch_mm: float = 8.0, height_mm: float = 9.6,
                  stud_radius_mm: float = 2.4, stud_height_mm: float = 1.7) -> trimesh.Trimesh:
    """A Lego-like brick upside down: its studs press into the gel."""
    body = trimesh.creation.box((studs_x * pitch_mm - 0.2, studs_y * pitch_mm - 0.2, height_mm))
    studs = []
    for i in range(studs_x):
        for j in range(studs_y):
            s = trimesh.creation.cylinder(radius=stud_radius_mm, height=stud_height_mm, sections=SECTIONS)
            s.apply_translation([(i - (studs_x - 1) / 2) * pitch_mm, (j - (studs_y - 1) / 2) * pitch_mm,
                                 -(height_mm + stud_height_mm) / 2])
            studs.append(s)
    return _centred(_union(body, *studs))


def pocket_block(side_mm: float = 12.0, height_mm: float = 6.0, pocket_side_mm: float = 6.0, pocket_depth_mm: float = 1.5) -> trimesh.Trimesh:
    """A block whose bottom face has a square recessed pocket: the gel bulges into it."""
    block = trimesh.creation.box((side_mm, side_mm, height_mm))
    cut = trimesh.creation.box((pocket_side_mm, pocket_side_mm, 2 * pocket_depth_mm))
    cut.apply_translation([0, 0, -height_mm / 2])
    return _centred(trimesh.boolean.difference([block, cut], engine="manifold"))


@dataclass(frozen=True)
class IndenterSpec:
    build: Callable[[], trimesh.Trimesh]
    volume_mm3: float  # of the ideal solid
    description: str


def _ring_area(r_out: float, width: float) -> float:
    return pi * (r_out**2 - (r_out - width) ** 2)


#: The library: file stem in ``scenes/indenters/`` -> how to build it and its exact volume.
LIBRARY: dict[str, IndenterSpec] = {
    "sphere_r4": IndenterSpec(sphere, 4 / 3 * pi * 4.0**3, "sphere, radius 4 mm"),
    "cylinder_r3_l16": IndenterSpec(cylinder, pi * 3.0**2 * 16.0, "roller, radius 3 mm, 16 mm long, axis y"),
    "flat_punch_r3": IndenterSpec(flat_punch, pi * 3.0**2 * 6.0, "flat circular punch, radius 3 mm"),
    "cube_edge_6": IndenterSpec(cube_edge, 6.0**3, "6 mm cube, an edge down"),
    "cone_r4_h6": IndenterSpec(cone, _rounded_cone_volume(4.0, 6.0, 0.5),
                               "cone, tip down, base radius 4 mm, 6 mm to the apex, tip rounded to 0.5 mm"),
    "coin_r11.6": IndenterSpec(coin, pi * 11.6**2 * 1.6 + _ring_area(11.6, 1.0) * 0.4, "coin with a raised rim"),
    "brick_2x2": IndenterSpec(studded_brick, 15.8**2 * 9.6 + 4 * pi * 2.4**2 * 1.7, "Lego-like 2x2 brick, studs down"),
    "pocket_block_12": IndenterSpec(pocket_block, 12.0**2 * 6.0 - 6.0**2 * 1.5, "block with a 6 mm recessed pocket"),
}


def polygon_volume_ratio(sections: int = SECTIONS) -> float:
    """Area of a regular ``sections``-gon inscribed in the unit circle over the circle's area."""
    return sections / (2 * pi) * np.sin(2 * pi / sections)
