"""Per-frame dense fusion for ``reconstruct``: dense points of the white-light pair (``stereo.dense``: SGBM or
a local ONNX stereo model) aligned (``stereo.dense``'s module docstring says how) to the frame's anchors (``stereo.anchors``: the triangulated markers, plus
with ``anchors="distance-aware"`` triangulated object features beyond the gel), written as a depth map
``<stem>.exr`` (z in the left camera frame, mm, on the rectified left grid, +inf where no point) and a point
cloud ``<stem>.ply`` (mm, left camera frame)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from transtac_sim.perception.stereo.anchors import distance_aware_anchors
from transtac_sim.perception.stereo.calibration import StereoCalibration
from transtac_sim.perception.stereo.dense import (
    OnnxStereo,
    align_to_anchors,
    dense_points,
    fit_similarity,
    write_depth_exr,
    write_ply,
)
from transtac_sim.perception.stereo.triangulation import FlatStack, triangulate_linear

ANCHOR_MODES = ("markers", "distance-aware")


def fuse_frame(calib: StereoCalibration, left_white: np.ndarray, right_white: np.ndarray, left_uv: np.ndarray,
               right_uv: np.ndarray, xyz_mm: np.ndarray, stem: Path, *, stack: FlatStack | None = None,
               model: OnnxStereo | None = None, anchors: str = "markers") -> tuple[dict, np.ndarray | None]:
    """(the frame's ``dense`` record, the fused depth map or None). ``left_uv``, ``right_uv``, ``xyz_mm``: the
    matched markers (recorded pixels, their 3D points). Distance-aware anchors need ``stack``."""
    if len(xyz_mm) < 3:
        return {"aligned": False, "reason": "fewer than 3 triangulated markers"}, None
    d_ref = float(np.median(calib.rectified(left_uv, "left")[:, 0] - calib.rectified(right_uv, "right")[:, 0]))
    points = dense_points(calib, left_white, right_white, d_ref, model=model)
    whites = (left_white, right_white) if anchors == "distance-aware" else (None, None)
    a = distance_aware_anchors(calib, stack, left_uv, right_uv, xyz_mm, *whites)
    if model is not None:  # a learned model's points may carry its own bias: fit the dense map itself
        fit = align_to_anchors(points, calib, a.left_uv, a.xyz_mm, a.tolerance_mm)
    else:  # SGBM is pinhole geometry: fit the anchors' own pinhole triangulations (no dense noise on dots)
        fit = fit_similarity(triangulate_linear(calib, a.left_uv, a.right_uv), a.xyz_mm, a.tolerance_mm)
    if fit is None:
        return {"aligned": False, "reason": "no similarity found (fewer than 3 consistent anchors)"}, None
    fused = fit.apply(points.xyz_mm.reshape(-1, 3)).reshape(points.xyz_mm.shape)
    depth = np.where(points.valid, fused[:, :, 2], np.inf)
    write_depth_exr(stem.with_suffix(".exr"), depth)
    write_ply(stem.with_suffix(".ply"), fused[points.valid])
    features = int((~a.is_marker).sum())
    return {"aligned": True, "method": "onnx" if model is not None else "sgbm", "anchors": anchors,
            "scale": fit.scale, "anchor_pairs": fit.pairs, "feature_anchors": features, "inliers": fit.inliers,
            "rms_mm": fit.rms_mm, "valid_fraction": float(points.valid.mean())}, depth
