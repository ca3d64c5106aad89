"""Stereo calibration from chessboard images of both cameras (OpenCV), written as ``calibration.json``
with the datasets' keys (``docs/formats.md``).

Per image pair: the board's inner corners found in both views (``cv2.findChessboardCornersSB``, sub-pixel);
pairs where either view misses the board are skipped. Each camera's intrinsics by ``cv2.calibrateCamera``
(pinhole with k1, k2, p1, p2, k3), then ``cv2.stereoCalibrate`` with the intrinsics fixed gives R, T
(x_right = R x_left + T, mm when ``square_mm`` is in mm). The report gives the RMS reprojection errors.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.perception.errors import PerceptionInputError, output_file
from transtac_sim.perception.images import find_images, read_image
from transtac_sim.writer.atomic import write_json

MIN_PAIRS = 4


@dataclass
class CalibrationReport:
    out: Path
    pairs_used: int
    pairs_total: int
    rms_left_px: float
    rms_right_px: float
    rms_stereo_px: float
    baseline_mm: float
    focal_px: tuple[float, float]


def find_corners(image: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """(N, 2) sub-pixel inner corners of a ``board`` = (columns, rows) chessboard in an 8-bit grey (H, W) or BGR
    (H, W, 3) image, or None."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    found, corners = cv2.findChessboardCornersSB(gray, board, flags=cv2.CALIB_CB_ACCURACY)
    return corners.reshape(-1, 2).astype(np.float32) if found else None


def calibrate_stereo(left: Path, right: Path, out: Path, board: tuple[int, int], square_mm: float) -> CalibrationReport:
    out = output_file(out)
    refs_l, refs_r = find_images(Path(left)), find_images(Path(right))
    if len(refs_l) != len(refs_r):
        raise PerceptionInputError(f"{left}, {right}", f"{len(refs_l)} left images but {len(refs_r)} right images",
                                   "give both cameras the same board views (paired in sorted order)")
    grid = np.zeros((board[0] * board[1], 3), np.float32)
    grid[:, :2] = np.mgrid[0:board[0], 0:board[1]].T.reshape(-1, 2) * square_mm
    pts_l, pts_r, size = [], [], None
    for a, b in zip(refs_l, refs_r, strict=True):
        im_l, im_r = read_image(a.path), read_image(b.path)
        s = (im_l.shape[1], im_l.shape[0])
        if size is None:
            size = s
        if s != size or (im_r.shape[1], im_r.shape[0]) != size:
            raise PerceptionInputError(b.path, f"image size differs from the first image's {size[0]}x{size[1]}",
                                       "calibrate with images of one size")
        c_l, c_r = find_corners(im_l, board), find_corners(im_r, board)
        if c_l is not None and c_r is not None:
            pts_l.append(c_l)
            pts_r.append(c_r)
    if len(pts_l) < MIN_PAIRS:
        raise PerceptionInputError(left, f"the {board[0]}x{board[1]} board was found in both views of only {len(pts_l)} "
                                   f"of {len(refs_l)} pairs (at least {MIN_PAIRS} needed)",
                                   "check --board (inner corners, columns x rows) and take more views")
    obj = [grid] * len(pts_l)
    try:
        rms_l, K_l, d_l, _, _ = cv2.calibrateCamera(obj, pts_l, size, None, None)
        rms_r, K_r, d_r, _, _ = cv2.calibrateCamera(obj, pts_r, size, None, None)
        rms, K_l, d_l, K_r, d_r, R, T, _, _ = cv2.stereoCalibrate(
            obj, pts_l, pts_r, K_l, d_l, K_r, d_r, size, flags=cv2.CALIB_FIX_INTRINSIC)
    except cv2.error as e:
        raise PerceptionInputError(left, f"OpenCV could not calibrate from these views ({e.err})",
                                   "check --board and --square-mm, and take views of the board at other angles"
                                   ) from None
    write_json(Path(out), {"image_size": list(size), "model": "pinhole", "K_left": K_l.tolist(), "dist_left": d_l.ravel().tolist(),
                           "K_right": K_r.tolist(), "dist_right": d_r.ravel().tolist(), "R": R.tolist(),
                           "T": T.ravel().tolist(), "units": "mm", "rms_px": float(rms)})
    return CalibrationReport(Path(out), len(pts_l), len(refs_l), float(rms_l), float(rms_r), float(rms),
                             float(np.linalg.norm(T)), (float(K_l[0, 0]), float(K_r[0, 0])))
