"""Distance-aware anchors for aligning dense stereo to metric 3D: markers near the gel, image features on
the object farther away (the TransTac paper's fusion).

Dense stereo on the white-light pair is a pinhole reconstruction: through the backing and the gel its
points are off by a distortion (about 2 mm in depth for the default stack). The markers (triangulated
through the flat stack, ``triangulation.triangulate_refracted``) pin it down at the gel; a similarity fitted
to them alone has to extrapolate to an object 10 mm beyond the gel. Feature anchors cover that range: SIFT
keypoints of both white images (OpenCV; ``feature_pairs``), matched by descriptor among the keypoints near
the same rectified row with a disparity below the markers' (farther than the gel); each is triangulated
through the whole stack, air | backing | gel | air beyond the gel's contact surface (``rays_beyond_gel``:
Snell's law at every interface, the contact surface taken flat, so only points off the gel's surface are
kept: ``min_height_mm`` to ``max_height_mm`` beyond it, the range the dense search covers).

Distance-aware weights: a pair of rays triangulated at depth z from a disparity error sigma_d (px) is off
in depth by about sigma_z = z^2 sigma_d / (f b) (f focal length in px, b baseline in mm). Each anchor's
RANSAC residual is divided by its own tolerance max(marker_tol_mm, z^2 sigma_d / (f b)): markers, close
and precise, count with ``marker_tol_mm``; far features with the wider tolerance their depth allows.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.perception.stereo.calibration import StereoCalibration
from transtac_sim.perception.stereo.dense import stretched_grey
from transtac_sim.perception.stereo.triangulation import (
    FlatStack,
    _closest_points_midpoint,
    rays_in_gel,
    refract,
    stereo_rays,
)


@dataclass(frozen=True)
class Anchors:
    """3D anchor points (K, 3) in the left camera frame (mm), their recorded left and right pixels (K, 2),
    the tolerance of each (K,) mm, and which are markers (K,) bool."""

    xyz_mm: np.ndarray
    left_uv: np.ndarray
    right_uv: np.ndarray
    tolerance_mm: np.ndarray
    is_marker: np.ndarray


def rays_beyond_gel(stack: FlatStack, centre: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays (unit ``directions`` (K, 3) from ``centre``, (3,) or one per ray, left frame) leave the
    gel's flat contact surface (K, 3) mm, and their unit directions in the air beyond it (K, 3)."""
    at_bond, d = rays_in_gel(stack, centre, directions)
    n = stack.normal
    at_surface = at_bond + (stack.gel_thickness_mm / (d @ n))[:, None] * d
    return at_surface, refract(d, n, stack.n_gel / stack.n_air)


def triangulate_beyond_gel(calib: StereoCalibration, stack: FlatStack, left_uv: np.ndarray,
                           right_uv: np.ndarray) -> np.ndarray:
    """Points (K, 3) mm, left camera frame, beyond the gel, of matched recorded pixels (K, 2)."""
    k = len(left_uv)
    p, d = rays_beyond_gel(stack, *stereo_rays(calib, left_uv, right_uv))
    return _closest_points_midpoint(p[:k], d[:k], p[k:], d[k:])


def feature_pairs(calib: StereoCalibration, left_bgr: np.ndarray, right_bgr: np.ndarray, max_disparity_px: float,
                  row_tol_px: float = 4.0, ratio: float = 0.8, max_features: int = 3000) -> tuple[np.ndarray, np.ndarray]:
    """Matched SIFT keypoints (K, 2) in the recorded left and right images (module docstring): images
    stretched and equalised (CLAHE), each left keypoint matched to the nearest right descriptor among those
    within ``row_tol_px`` of its rectified row and of disparity in (0, ``max_disparity_px``), accepted when
    it passes Lowe's ratio test and the match is mutual."""
    sift = cv2.SIFT_create(nfeatures=max_features, contrastThreshold=0.02)
    clahe = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8))
    (kl, dl), (kr, dr) = (sift.detectAndCompute(clahe.apply(stretched_grey(im)), None) for im in (left_bgr, right_bgr))
    if dl is None or dr is None or len(kl) < 2 or len(kr) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    lu, ru = np.array([k.pt for k in kl]), np.array([k.pt for k in kr])
    rl, rr = calib.rectified(lu, "left"), calib.rectified(ru, "right")
    disparity = rl[:, None, 0] - rr[None, :, 0]
    gate = (np.abs(rl[:, None, 1] - rr[None, :, 1]) <= row_tol_px) & (disparity > 0) & (disparity < max_disparity_px)
    dist = np.full(gate.shape, np.inf)
    ii, jj = np.nonzero(gate)  # descriptor distances of the gated pairs only (not an N x M x 128 array)
    dist[ii, jj] = np.linalg.norm(dl[ii] - dr[jj], axis=1)
    order = np.argsort(dist, axis=1)[:, :2]
    rows = np.arange(len(dist))
    best, second = dist[rows, order[:, 0]], dist[rows, order[:, 1]]
    i = np.nonzero(np.isfinite(best) & (best < ratio * second))[0]
    j = order[i, 0]
    mutual = np.argmin(dist, axis=0)[j] == i
    return lu[i[mutual]], ru[j[mutual]]


def distance_aware_anchors(calib: StereoCalibration, stack: FlatStack | None, marker_left_uv: np.ndarray,
                           marker_right_uv: np.ndarray, marker_xyz_mm: np.ndarray,
                           left_white: np.ndarray | None = None, right_white: np.ndarray | None = None,
                           marker_tol_mm: float = 0.3, sigma_disparity_px: float = 0.5,
                           min_height_mm: float = 0.2, max_height_mm: float = 40.0) -> Anchors:
    """The markers (their recorded left and right pixels and 3D points), plus, with both white images,
    feature anchors beyond the gel, with their tolerances. Feature anchors need ``stack.gel_thickness_mm``."""
    xyz = [np.asarray(marker_xyz_mm, float).reshape(-1, 3)]
    uv = [np.asarray(marker_left_uv, float).reshape(-1, 2)]
    uv_right = [np.asarray(marker_right_uv, float).reshape(-1, 2)]
    tol = [np.full(len(xyz[0]), marker_tol_mm)]
    if left_white is not None and right_white is not None:
        if stack.gel_thickness_mm is None:
            raise PerceptionInputError("stack", "distance-aware anchors need the gel's thickness",
                                       'add "gel_thickness_mm" to the flat stack\'s JSON file')
        d_markers = np.median(calib.rectified(marker_left_uv, "left")[:, 0] - calib.rectified(marker_right_uv, "right")[:, 0])
        lu, ru = feature_pairs(calib, left_white, right_white, max_disparity_px=float(d_markers))
        if len(lu):
            p = triangulate_beyond_gel(calib, stack, lu, ru)
            surface = stack.point_mm @ stack.normal + stack.backing_thickness_mm + stack.gel_thickness_mm
            height = p @ stack.normal - surface
            keep = (height >= min_height_mm) & (height <= max_height_mm)
            p, lu, ru = p[keep], lu[keep], ru[keep]
            f_px = float(calib.K_left[0, 0])
            baseline = float(np.linalg.norm(calib.T))
            xyz.append(p)
            uv.append(lu)
            uv_right.append(ru)
            tol.append(np.maximum(marker_tol_mm, p[:, 2] ** 2 * sigma_disparity_px / (f_px * baseline)))
    n_markers = len(xyz[0])
    all_xyz = np.concatenate(xyz)
    return Anchors(all_xyz, np.concatenate(uv), np.concatenate(uv_right), np.concatenate(tol),
                   np.arange(len(all_xyz)) < n_markers)
