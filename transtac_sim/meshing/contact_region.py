"""The contact region: the xy rectangle (gel frame, mm) that the indenters can touch over their
trajectories, used to refine the mesh there.

Conservative: the footprint of each indenter at its start is swept along every slide and roll (their
displacements added up), and grown by the indenter's xy radius for any rotate segment; the union over
indenters is grown by the mesh's ``refine_margin_mm`` and clipped to the gel.
"""

from __future__ import annotations

from math import cos, radians, sin

import numpy as np

from transtac_sim.config.trajectory import Roll, Rotate, Slide
from transtac_sim.meshing.gel_mesh import Rect
from transtac_sim.scene_setup import SceneSetup


def contact_region(setup: SceneSetup) -> Rect | None:
    """None for a contact-free scene."""
    if not setup.indenters:
        return None
    w, h, _ = setup.sensor.gel_size_mm
    boxes = []
    for ind in setup.indenters:
        v = ind.mesh.mesh.vertices @ ind.start_pose[:3, :3].T + ind.start_pose[:3, 3]
        lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
        pos, path_lo, path_hi, grow = np.zeros(2), np.zeros(2), np.zeros(2), 0.0
        for seg in ind.config.trajectory:
            if isinstance(seg, (Slide, Roll)):
                a = radians(seg.direction_deg)
                pos = pos + seg.distance_mm * np.array([cos(a), sin(a)])
                path_lo, path_hi = np.minimum(path_lo, pos), np.maximum(path_hi, pos)
            elif isinstance(seg, Rotate):
                grow = max(grow, float(np.linalg.norm(hi - lo)) / 2)
        boxes.append((lo + path_lo - grow, hi + path_hi + grow))
    m = setup.scene.mesh.refine_margin_mm
    lo = np.min([b[0] for b in boxes], axis=0) - m
    hi = np.max([b[1] for b in boxes], axis=0) + m
    lo, hi = np.maximum(lo, [-w / 2, -h / 2]), np.minimum(hi, [w / 2, h / 2])
    if (lo >= hi).any():
        return None  # every indenter stays beside the gel
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
