"""Dense stereo and its fusion: SGBM depth of a textured plane at a known distance, the RANSAC + Umeyama
similarity recovered exactly despite outlying anchors and weighing each anchor by its own tolerance, the
triangulation beyond the gel, and the learned-stereo (ONNX) slot."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from transtac_sim.perception.stereo.calibration import calibration_from_dict
from transtac_sim.perception.stereo.dense import DensePoints, align_to_anchors, dense_points, fit_similarity

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
    assert dp.valid[:, 96:].mean() > 0.75  # the leftmost d columns are out of the right camera's view
    assert dp.valid[:, 96:160].mean() > 0.75  # not lost to SGBM's unmatched band (min + count columns)
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
    a = align_to_anchors(dense, calib, left_uv, markers, tolerance_mm=0.05)
    assert a is not None and a.inliers == 48 and a.pairs == 60
    assert a.scale == pytest.approx(s, abs=1e-9)
    assert np.allclose(a.rotation, R, atol=1e-9) and np.allclose(a.translation_mm, t, atol=1e-8)


def test_fit_weighs_each_anchor_by_its_own_tolerance():
    """A far anchor 0.8 mm off is an inlier within its 1.5 mm tolerance; the same error on a marker's
    0.05 mm tolerance is not, and the similarity comes from the consistent pairs only."""
    rng = np.random.default_rng(4)
    src = np.column_stack([rng.uniform(-8, 8, 40), rng.uniform(-6, 6, 40), rng.uniform(17, 30, 40)])
    s, R, t = 0.98, Rotation.from_euler("z", 1.0, degrees=True).as_matrix(), np.array([0.1, 0.0, 2.0])
    dst = s * src @ R.T + t
    tol = np.where(src[:, 2] > 25, 1.5, 0.05)
    far, near = np.nonzero(tol > 1)[0][0], np.nonzero(tol < 1)[0][0]
    dst[far] += [0.0, 0.0, 0.8]
    dst[near] += [0.0, 0.0, 0.8]
    a = fit_similarity(src, dst, tol)
    assert a is not None and a.inliers == 39 and a.pairs == 40
    assert a.scale == pytest.approx(s, abs=0.01)


def test_triangulation_beyond_the_gel_inverts_the_refracted_rays():
    """A point 6 mm beyond the gel, seen by both cameras through backing and gel (each ray bent at three
    interfaces, found by solving for the pixel whose traced ray passes through the point), is recovered."""
    from scipy.optimize import least_squares

    from transtac_sim.perception.stereo.anchors import rays_beyond_gel, triangulate_beyond_gel
    from transtac_sim.perception.stereo.triangulation import flat_stack_from_dict

    calib = _calib()
    stack = flat_stack_from_dict({"point_mm": [0, 0, 15.0], "normal": [0, 0, 1], "backing_thickness_mm": 2.0,
                                  "n_backing": 1.49, "n_gel": 1.41, "gel_thickness_mm": 5.0})
    target = np.array([1.5, -2.0, 28.0])

    def pixel_seeing(camera: str, centre: np.ndarray) -> np.ndarray:
        def miss(uv):
            xy = calib.normalised(uv[None], camera)
            d = np.append(xy[0], 1.0) @ (calib.R if camera == "right" else np.eye(3))
            p, dd = rays_beyond_gel(stack, centre, (d / np.linalg.norm(d))[None])
            s = (target[2] - p[0, 2]) / dd[0, 2]
            return (p[0] + s * dd[0])[:2] - target[:2]
        return least_squares(miss, np.array([160.0, 120.0]), xtol=1e-14, ftol=1e-14).x

    uv_l, uv_r = pixel_seeing("left", np.zeros(3)), pixel_seeing("right", calib.right_centre_mm)
    xyz = triangulate_beyond_gel(calib, stack, uv_l[None], uv_r[None])[0]
    assert np.linalg.norm(xyz - target) < 1e-6


def test_learned_stereo_slot_runs_a_local_onnx_model_and_refuses_a_missing_one(tmp_path):
    """An ONNX model answering a constant disparity d gives the plane z = f_rect B / d; a missing file is
    one clear error."""
    torch = pytest.importorskip("torch")
    from transtac_sim.perception.errors import PerceptionInputError
    from transtac_sim.perception.stereo.dense import OnnxStereo

    class Constant(torch.nn.Module):
        def forward(self, left, right):
            return left[:, :1] * 0.0 + right[:, :1] * 0.0 + 80.0

    path = tmp_path / "stereo.onnx"
    z = torch.zeros(1, 3, SIZE[1], SIZE[0])
    torch.onnx.export(Constant(), (z, z), str(path), input_names=["left", "right"], output_names=["disparity"],
                      dynamo=False)
    calib = _calib()
    img = np.full((SIZE[1], SIZE[0], 3), 128, np.uint8)
    dp = dense_points(calib, img, img, disparity_px=0.0, model=OnnxStereo(path))
    assert dp.valid.all()
    assert np.allclose(dp.xyz_mm[..., 2], calib.rectification.P1[0, 0] * BASELINE_MM / 80.0, rtol=1e-5)
    with pytest.raises(PerceptionInputError, match="not found"):
        OnnxStereo(tmp_path / "missing.onnx")
