"""The paper's two image-based baselines: dense correspondence from the images, snapped to detections.

Both rectify the pair (``StereoCalibration.rectification_maps``), stretch each image's grey levels to
0-255 (UV frames are dark: markers a few tens of grey levels over black) and give each left detection a
predicted position in the right rectified image, with the same disparity prior d_ref +- w as the point
matchers (``matching``: from ``MatchParams`` or estimated from the detections):
- ``farneback``: ``cv2.calcOpticalFlowFarneback`` from the left to the right image, started at (-d_ref, 0);
  prediction p + flow(p);
- ``sgbm``: ``cv2.StereoSGBM`` disparity d(p) (left reference) searched over d_ref +- w; prediction
  p - (d, 0).
The flow or disparity is sampled at the left detection's rectified position p (nearest pixel). The
right detection nearest the prediction is its match when it lies within ``SNAP_PX``; a right detection
claimed twice goes to the nearer prediction. Points whose disparity is invalid (SGBM's negative values)
stay unmatched. No epipolar gate: the images, not ``MatchParams``, decide (as in the paper's baselines).

They need the images, so they are built per frame: ``image_matcher(name, left_image, right_image)``
returns a function with the point matchers' signature (``matching.Matcher``). Images are 8-bit BGR or
grey, in the recorded (distorted) geometry of ``calib``.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np
from scipy.spatial import cKDTree

from transtac_sim.perception.stereo.calibration import StereoCalibration, check_image_size
from transtac_sim.perception.stereo.matching import Matcher, MatchParams, candidates, no_pairs

SNAP_PX = 6.0


def rectified_grey(calib: StereoCalibration, image: np.ndarray, camera: str) -> np.ndarray:
    """``image`` of ``camera`` rectified, grey, stretched to 0-255 (uint8)."""
    check_image_size(calib, (image.shape[1], image.shape[0]), f"{camera} image")
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    rect = cv2.remap(grey, *calib.rectification_maps[camera], cv2.INTER_LINEAR)
    return cv2.normalize(rect, None, 0, 255, cv2.NORM_MINMAX)


def farneback_field(left: np.ndarray, right: np.ndarray, d_ref: float, halfwidth: float) -> np.ndarray:
    """(h, w, 2) offset (px) from each left rectified pixel to the right image: optical flow started at
    (-d_ref, 0) (from zero it finds none of the ~150 px marker displacements of a 640x480 TransTac)."""
    init = np.zeros((*left.shape, 2), np.float32)
    init[..., 0] = -d_ref
    return cv2.calcOpticalFlowFarneback(left, right, init, pyr_scale=0.5, levels=6, winsize=31, iterations=5,
                                        poly_n=7, poly_sigma=1.5,
                                        flags=cv2.OPTFLOW_USE_INITIAL_FLOW | cv2.OPTFLOW_FARNEBACK_GAUSSIAN)


def sgbm_field(left: np.ndarray, right: np.ndarray, d_ref: float, halfwidth: float) -> np.ndarray:
    """(h, w, 2) offset (px) (-d, 0) from the SGBM disparity d searched over d_ref +- halfwidth (rounded
    out to OpenCV's multiples of 16); NaN where SGBM gives none."""
    block, lo = 7, max(int(np.floor(d_ref - halfwidth)), 0)
    count = 16 * int(np.ceil((d_ref + halfwidth - lo) / 16))
    sgbm = cv2.StereoSGBM_create(minDisparity=lo, numDisparities=count, blockSize=block, P1=8 * block**2,
                                 P2=32 * block**2, uniquenessRatio=5, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    # SGBM leaves the leftmost minDisparity + numDisparities columns unmatched: both images padded by that much
    # on the left (as dense.py ``sgbm_disparity``), so markers there are matched too
    pad = lo + count
    left_p, right_p = (cv2.copyMakeBorder(g, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0) for g in (left, right))
    d = sgbm.compute(left_p, right_p)[:, pad:].astype(np.float32) / 16.0  # fixed point, 4 fractional bits
    d[d < lo] = np.nan
    return np.dstack([-d, np.zeros_like(d)])


FIELDS: dict[str, Callable[[np.ndarray, np.ndarray, float, float], np.ndarray]] = {
    "farneback": farneback_field, "sgbm": sgbm_field}


def snap(predicted: np.ndarray, right_rect: np.ndarray) -> np.ndarray:
    """Pairs (K, 2): each left point to the right point (M, 2) nearest its prediction (N, 2), rectified
    px, within ``SNAP_PX``; a right point claimed twice goes to the nearer prediction."""
    ok = np.all(np.isfinite(predicted), axis=1)
    if len(right_rect) == 0 or not ok.any():
        return no_pairs()
    dist, j = cKDTree(right_rect).query(predicted[ok])
    i = np.flatnonzero(ok)
    keep = dist <= SNAP_PX
    i, j, dist = i[keep], j[keep], dist[keep]
    order = np.argsort(dist, kind="stable")
    _, first = np.unique(j[order], return_index=True)
    pick = np.sort(order[first])
    return np.column_stack([i[pick], j[pick]]).astype(np.int64)


def image_matcher(name: str, left_image: np.ndarray, right_image: np.ndarray) -> Matcher:
    """The ``farneback`` or ``sgbm`` matcher of one stereo frame (module docstring)."""
    field = FIELDS[name]

    def match(left_uv: np.ndarray, right_uv: np.ndarray, calib: StereoCalibration,
              params: MatchParams = MatchParams()) -> np.ndarray:
        c = candidates(left_uv, right_uv, calib, params)
        if len(c.left) == 0 or not np.isfinite(c.d_ref):
            return no_pairs()
        offset = field(rectified_grey(calib, left_image, "left"), rectified_grey(calib, right_image, "right"),
                       c.d_ref, params.disparity_halfwidth_px)
        h, w = offset.shape[:2]
        x, y = np.clip(np.round(c.left).astype(int), 0, [w - 1, h - 1]).T
        return snap(c.left + offset[y, x], c.right)

    return match
