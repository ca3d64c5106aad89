"""Mitsuba perspective sensors that reproduce an OpenCV pinhole K exactly.

Mitsuba's film coordinates put pixel i's centre at i + 0.5 (OpenCV: at i), ``fov`` spans the whole
film width along ``fov_axis`` = "x", and ``principal_point_offset_x/y`` shift the optical axis in
fractions of the film size. So for a square-pixel K = [[f, 0, cx], [0, f, cy], [0, 0, 1]] and a film
W x H: fov = 2 atan(W / (2 f)), offset_x = 0.5 - (cx + 0.5) / W, offset_y = 0.5 - (cy + 0.5) / H
(checked in tests/test_render_camera.py by rendering a point and finding it at K's projection).
The camera looks along +z of its OpenCV frame with y down: Mitsuba's ``look_at`` gets up = -y.
The film's reconstruction filter is a tent of radius 1 px: its weights reproduce linear functions, so the
intensity centroid of a rendered blob equals the centroid of the continuous image exactly (a box filter,
the plain pixel integral, biases centroids of sub-pixel detail towards pixel centres by up to ~0.05 px).
"""

from __future__ import annotations

import numpy as np


def perspective_sensor(mi, K: np.ndarray, size: tuple[int, int], R: np.ndarray, T: np.ndarray, spp: int = 16,
                       sampler: str = "independent"):
    """Mitsuba sensor for a square-pixel pinhole ``K``, film ``size`` (w, h), extrinsics x_cam = R x_world + T."""
    K, R, T = np.asarray(K, float), np.asarray(R, float), np.asarray(T, float)
    if not np.isclose(K[0, 0], K[1, 1]) or K[0, 1] != 0:
        raise ValueError("Mitsuba's perspective sensor needs square pixels (fx = fy, no skew)")
    w, h = size
    C = -R.T @ T
    return mi.load_dict({
        "type": "perspective",
        "fov": float(np.degrees(2 * np.arctan(w / (2 * K[0, 0])))),
        "fov_axis": "x",
        "principal_point_offset_x": float(0.5 - (K[0, 2] + 0.5) / w),
        "principal_point_offset_y": float(0.5 - (K[1, 2] + 0.5) / h),
        "near_clip": 0.01,
        "far_clip": 1e4,
        "to_world": mi.ScalarTransform4f().look_at(origin=C.tolist(), target=(C + R.T @ [0, 0, 1.0]).tolist(),
                                                  up=(-(R.T @ [0, 1.0, 0])).tolist()),
        "film": {"type": "hdrfilm", "width": int(w), "height": int(h), "pixel_format": "rgb",
                 "rfilter": {"type": "tent"}, "sample_border": False},
        "sampler": {"type": sampler, "sample_count": int(spp)},
    })
