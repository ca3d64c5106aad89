"""Dense stereo and its fusion with the markers: SGBM depth of a textured plane at a known distance, and
the RANSAC + Umeyama similarity recovered exactly despite outlying anchors."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from transtac_sim.perception.stereo.calibration import calibration_from_dict
from transtac_sim.perception.stereo.dense import DensePoints, align_to_markers, dense_points

F_PX, BASELINE_MM, SIZE = 200.0, 12.0, (320, 240)


def _calib():
    k = [[F_PX, 0.0, 159.5], [0.0, F_PX, 119.5], [0.0, 0.0, 1.0]]
    return calibration_from_dict({"image_size": list(SIZE), "model": "pinhole", "K_left": k, "dist_left": [0.0] * 5,
                                  "K_right": k, "dist_right": [0.0] * 5, "R": np.eye(3).tolist(),
                                  "T": [-BASELINE_MM, 0.0, 0.0]})


def test_sgbm_depth_of_a_textured_plane():
    calib = _calib()
    d = 96.0  # px: a plane at z = f B / d = 25 mm
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.uniform(0, 255, (SIZE[1], SIZE[0] + 128)).astype(np.float32), (0, 0), 1.2)
    left = tex[:, 0:SIZE[0]]
    right = tex[:, 96:96 + SIZE[0]]  # right[x] = left[x + d]: a point at x_left is seen at x_left - d
    to8 = lambda a: np.repeat(np.clip(a, 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)  # noqa: E731
    dp = dense_points(calib, to8(left), to8(right), disparity_px=d - 5.0)
    f_rect = calib.rectification.P1[0, 0]
    z = dp.xyz_mm[..., 2][dp.valid]
    assert dp.valid.mean() > 0.45  # SGBM leaves the leftmost min + count disparities unmatched
    assert np.median(z) == pytest.approx(f_rect * BASELINE_MM / d, rel=0.01)


def test_alignment_recovers_a_similarity_with_outliers():
    calib = _calib()
    h, w = SIZE[1], SIZE[0]
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    field = np.stack([0.05 * xs - 8.0, 0.05 * ys - 6.0, 20.0 + 0.01 * xs], axis=2)  # linear: 3x3 median = centre
    dense = DensePoints(field, np.ones((h, w), bool))
    rng = np.random.default_rng(1)
    left_uv = rng.uniform([20, 20], [w - 20, h - 20], (60, 2))
    rect = np.rint(calib.rectified(left_uv, "left")).astype(int)
    src = field[rect[:, 1], rect[:, 0]]
    s, R, t = 1.03, Rotation.from_euler("xyz", [2.0, -1.5, 3.0], degrees=True).as_matrix(), np.array([0.4, -0.2, 2.1])
    markers = s * src @ R.T + t
    markers[:12] += rng.uniform(1.0, 3.0, (12, 3))  # 20 % wrong anchors
    a = align_to_markers(dense, calib, left_uv, markers, threshold_mm=0.05)
    assert a is not None and a.inliers == 48 and a.pairs == 60
    assert a.scale == pytest.approx(s, abs=1e-9)
    assert np.allclose(a.rotation, R, atol=1e-9) and np.allclose(a.translation_mm, t, atol=1e-8)
