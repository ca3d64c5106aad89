"""Where an indenter starts: its pose in the gel frame before the first trajectory segment."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from transtac_sim.config import ConfigError
from transtac_sim.config.scene import Indenter
from transtac_sim.indenters.loading import IndenterMesh


def start_pose(cfg: Indenter, mesh: IndenterMesh, gel_size_mm: tuple[float, float, float],
               *, source: str, key: str) -> np.ndarray:
    """4x4 pose (indenter frame -> gel frame, mm): turned by ``rotation_deg`` (extrinsic x, y, z), origin
    above ``start_xy_mm`` and lowest point ``start_gap_mm`` above the contact surface z = thickness.

    An indenter whose start overlaps the gel is refused with a ConfigError naming ``source`` and ``key``.
    """
    w, h, t = gel_size_mm
    R = Rotation.from_euler("xyz", cfg.rotation_deg, degrees=True).as_matrix()
    v = mesh.mesh.vertices @ R.T
    pose = np.eye(4)
    pose[:3, :3] = R
    pose[:3, 3] = [cfg.start_xy_mm[0], cfg.start_xy_mm[1], t + cfg.start_gap_mm - v[:, 2].min()]
    lo, hi = (v + pose[:3, 3]).min(axis=0), (v + pose[:3, 3]).max(axis=0)
    overlaps_footprint = lo[0] < w / 2 and hi[0] > -w / 2 and lo[1] < h / 2 and hi[1] > -h / 2
    if cfg.start_gap_mm < 0 and overlaps_footprint:
        raise ConfigError(source, [(
            f"{key}.start_gap_mm",
            f"{cfg.start_gap_mm} puts the indenter {-cfg.start_gap_mm:g} mm inside the gel at the start; "
            "a trajectory must start outside (allowed: start_gap_mm >= 0; use a press segment to go in)",
        )])
    return pose
