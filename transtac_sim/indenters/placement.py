"""Where an indenter starts: its pose in the gel frame before the first trajectory segment.

The point placed over ``start_xy_mm`` is the indenter's anchor (``Indenter.anchor`` in the scene file):

- ``"footprint"`` (default): the centre of its footprint, i.e. the midpoint of the xy bounding box of the
  vertices within ``FOOTPRINT_DEPTH_MM`` of its lowest point, after ``rotation_deg``. That is the part a
  press touches, so the contact lies at ``start_xy_mm`` whatever the mesh's origin (CAD files often put it
  far from the body) and however the body is tilted; a bounding box of the whole body would put a stylus
  tip or a tilted edge beside it. The bounding box of those vertices (not their mean) does not depend on
  how finely a face is triangulated.
- ``"origin"``: the mesh file's origin.

The library indenters (``scenes/indenters/``) are centred and symmetric under a half turn about z, so for
them, turned about z only, both anchors give the same pose (the anchor is rounded to 1e-6 mm, about the
float32 resolution of an STL's coordinates at 10 mm, so that the round-off of a symmetric mesh does not move it).
The indenter's frame (its poses, ``pose_mm`` in labels) is the mesh file's frame with either anchor.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from transtac_sim.config import ConfigError
from transtac_sim.config.scene import Indenter
from transtac_sim.indenters.loading import IndenterMesh

#: The footprint: the vertices at most this far above the lowest one (mm), what a typical press reaches.
FOOTPRINT_DEPTH_MM = 0.5
#: Anchors are rounded to this (mm).
ANCHOR_RESOLUTION_DECIMALS = 6


def footprint_centre_xy(vertices_mm: np.ndarray) -> np.ndarray:
    """Centre (x, y) of the footprint (module docstring) of a body whose vertices (N, 3) are given in a
    frame with z along the gel's normal (mm, in the same frame)."""
    v = np.asarray(vertices_mm, dtype=np.float64)
    low = v[v[:, 2] <= v[:, 2].min() + FOOTPRINT_DEPTH_MM, :2]
    return (low.min(axis=0) + low.max(axis=0)) / 2.0


def start_pose(cfg: Indenter, mesh: IndenterMesh, gel_size_mm: tuple[float, float, float],
               *, source: str, key: str) -> np.ndarray:
    """4x4 pose (indenter frame -> gel frame, mm): turned by ``rotation_deg`` (extrinsic x, y, z, about the
    mesh origin), its anchor (``cfg.anchor``) above ``start_xy_mm`` and its lowest point ``start_gap_mm``
    above the contact surface z = thickness.

    An indenter whose start overlaps the gel is refused with a ConfigError naming ``source`` and ``key``.
    """
    w, h, t = gel_size_mm
    R = Rotation.from_euler("xyz", cfg.rotation_deg, degrees=True).as_matrix()
    v = mesh.mesh.vertices @ R.T
    anchor = np.round(footprint_centre_xy(v), ANCHOR_RESOLUTION_DECIMALS) if cfg.anchor == "footprint" else np.zeros(2)
    pose = np.eye(4)
    pose[:3, :3] = R
    pose[:3, 3] = [cfg.start_xy_mm[0] - anchor[0], cfg.start_xy_mm[1] - anchor[1], t + cfg.start_gap_mm - v[:, 2].min()]
    lo, hi = (v + pose[:3, 3]).min(axis=0), (v + pose[:3, 3]).max(axis=0)
    overlaps_footprint = lo[0] < w / 2 and hi[0] > -w / 2 and lo[1] < h / 2 and hi[1] > -h / 2
    if cfg.start_gap_mm < 0 and overlaps_footprint:
        raise ConfigError(source, [(
            f"{key}.start_gap_mm",
            f"{cfg.start_gap_mm} puts the indenter {-cfg.start_gap_mm:g} mm inside the gel at the start; "
            "a trajectory must start outside (allowed: start_gap_mm >= 0; use a press segment to go in)",
        )])
    return pose
