"""Dense stereo on the white-light pair and its alignment to the triangulated markers.

Dense points (``dense_points``): both images rectified (``StereoCalibration.rectification_maps``), OpenCV's
semi-global matching (SGBM) searches disparities d_ref +- ``halfwidth_px`` (d_ref: the markers' median
rectified disparity), ``cv2.reprojectImageTo3D`` with Q gives points in the rectified left frame, turned
into the left camera frame by R1^T (x_rect = R1 x_left). These are pinhole points: through the backing
and gel they are off by a similarity-like distortion of a few millimetres.

Fusion (``align_to_markers``): the dense point under each triangulated marker (median of the valid points
in a 3x3 window at its rectified position) is paired with the marker's 3D position, and a similarity
x' = s R x + t is fitted to those pairs by RANSAC (scikit-image's ``ransac``) around Umeyama's
least-squares similarity (``SimilarityTransform``), with inliers within ``threshold_mm``. Applying it to
every dense point gives the fused point cloud and depth map (z in the left camera frame, mm, on the
rectified left image grid). Markers are the anchors; image features on the object farther from the gel
(the paper's distance-aware anchors) are not used yet.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from transtac_sim.perception.stereo.calibration import StereoCalibration


@dataclass(frozen=True)
class DensePoints:
    xyz_mm: np.ndarray  # (H, W, 3) left camera frame, on the rectified left grid
    valid: np.ndarray  # (H, W) bool


@dataclass(frozen=True)
class Alignment:
    scale: float
    rotation: np.ndarray  # (3, 3)
    translation_mm: np.ndarray  # (3,)
    pairs: int
    inliers: int
    rms_mm: float  # of the inlier pairs after alignment

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        return self.scale * xyz @ self.rotation.T + self.translation_mm


def _grey(image_bgr: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr


def dense_points(calib: StereoCalibration, left_bgr: np.ndarray, right_bgr: np.ndarray, disparity_px: float,
                 halfwidth_px: int = 32, block_px: int = 5) -> DensePoints:
    maps = calib.rectification_maps
    left = cv2.remap(_grey(left_bgr), *maps["left"], cv2.INTER_LINEAR)
    right = cv2.remap(_grey(right_bgr), *maps["right"], cv2.INTER_LINEAR)
    lo = int(np.floor(disparity_px - halfwidth_px))
    count = int(np.ceil(2 * halfwidth_px / 16.0)) * 16
    sgbm = cv2.StereoSGBM_create(minDisparity=lo, numDisparities=count, blockSize=block_px,
                                 P1=8 * block_px**2, P2=32 * block_px**2, uniquenessRatio=5,
                                 speckleWindowSize=50, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    disparity = sgbm.compute(left, right).astype(np.float32) / 16.0
    valid = disparity >= lo
    xyz_rect = cv2.reprojectImageTo3D(disparity, calib.rectification.Q)
    xyz = xyz_rect @ calib.rectification.R1  # row vectors: x_left = R1^T x_rect
    return DensePoints(xyz.astype(np.float64), valid & np.isfinite(xyz).all(axis=2))


def align_to_markers(dense: DensePoints, calib: StereoCalibration, left_uv: np.ndarray, markers_xyz_mm: np.ndarray,
                     threshold_mm: float = 0.3, seed: int = 0) -> Alignment | None:
    """The similarity taking dense points onto the markers, or None with fewer than 3 usable pairs."""
    from skimage.measure import ransac
    from skimage.transform import SimilarityTransform

    h, w = dense.valid.shape
    rect = np.rint(calib.rectified(np.asarray(left_uv, dtype=np.float64).reshape(-1, 2), "left")).astype(int)
    src, dst = [], []
    for (u, v), x in zip(rect, np.asarray(markers_xyz_mm).reshape(-1, 3), strict=True):
        y0, y1, x0, x1 = max(v - 1, 0), min(v + 2, h), max(u - 1, 0), min(u + 2, w)
        if y0 >= y1 or x0 >= x1:
            continue
        ok = dense.valid[y0:y1, x0:x1]
        if ok.any():
            src.append(np.median(dense.xyz_mm[y0:y1, x0:x1][ok], axis=0))
            dst.append(x)
    if len(src) < 3:
        return None
    src, dst = np.array(src), np.array(dst)
    model, inliers = ransac((src, dst), SimilarityTransform, min_samples=3, residual_threshold=threshold_mm,
                            max_trials=500, rng=seed)
    if model is None or inliers is None or inliers.sum() < 3:
        return None
    m = model.params
    scale = float(np.cbrt(np.linalg.det(m[:3, :3])))
    rot = m[:3, :3] / scale
    res = np.linalg.norm(scale * src[inliers] @ rot.T + m[:3, 3] - dst[inliers], axis=1)
    return Alignment(scale, rot, m[:3, 3].copy(), len(src), int(inliers.sum()), float(np.sqrt(np.mean(res**2))))


def write_ply(path, xyz_mm: np.ndarray) -> None:
    """Binary little-endian PLY of points (N, 3), float32, mm."""
    from pathlib import Path

    from transtac_sim.writer.atomic import atomic_write

    pts = np.ascontiguousarray(xyz_mm, dtype="<f4").reshape(-1, 3)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment units mm, left camera frame\nelement vertex {len(pts)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    atomic_write(Path(path), lambda f: (f.write(header), f.write(pts.tobytes())))


def write_depth_exr(path, depth_mm: np.ndarray) -> None:
    """Single-channel float32 EXR named ``Z`` (mm), +inf where there is no point (as the datasets' depth)."""
    from pathlib import Path

    import OpenEXR

    from transtac_sim.writer.atomic import atomic_write

    atomic_write(Path(path), lambda f: OpenEXR.File(
        {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION},
        {"Z": np.ascontiguousarray(depth_mm, dtype=np.float32)}).write(f))
