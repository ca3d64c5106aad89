"""A stereo pair's calibration (``calibration.json``), its rectification, and point coordinates in it.

Conventions (DESIGN.md section 3): pixels in the recorded (distorted) image, OpenCV convention (the centre
of the top-left pixel is (0, 0), u right, v down); the left camera's OpenCV frame (x right, y down,
z forward, mm) is the reference and the right camera is at ``x_right = R x_left + T`` (``T`` in mm).

Rectification (``cv2.stereoRectify``, or ``cv2.fisheye.stereoRectify`` for the fisheye model) gives the
rotations ``R1``, ``R2`` of the two cameras into a common frame whose x axis is the baseline and the
projections ``P1``, ``P2`` of that frame. A point seen at recorded pixel p in the left camera has the
rectified pixel ``P1 (R1 undistort(p))``; for an ideal pinhole stereo pair a 3D point's two rectified
images share their y and differ in x by the disparity d = f B / z' (z' the rectified depth). Through the
TransTac's backing and gel the rays bend, so true pairs differ in y by up to a few pixels: matchers use a
tolerance, and ``triangulation`` removes the offset with refraction-aware rays.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.perception.errors import PerceptionInputError

MODELS = ("pinhole", "fisheye")
_SHAPES = {"K_left": (3, 3), "K_right": (3, 3), "R": (3, 3), "T": (3,)}
_DIST_LENGTHS = {"pinhole": (4, 5, 8, 12, 14), "fisheye": (4,)}
_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)


@dataclass(frozen=True)
class Rectification:
    """``cv2.stereoRectify``'s output: rotations R1, R2 (camera -> rectified frame), projections P1, P2
    (3x4, px) and the disparity-to-depth matrix Q; rectified images are ``image_size`` (w, h) px."""

    R1: np.ndarray
    R2: np.ndarray
    P1: np.ndarray
    P2: np.ndarray
    Q: np.ndarray
    image_size: tuple[int, int]

    @property
    def focal_px(self) -> float:
        """Rectified focal length (px)."""
        return float(self.P1[0, 0])

    @property
    def baseline_mm(self) -> float:
        """Baseline (mm) from P2 = [f 0 cx f*Tx; ...]: B = -Tx."""
        return float(-self.P2[0, 3] / self.P2[0, 0])


@dataclass(frozen=True, eq=False)
class StereoCalibration:
    """A dataset's ``calibration.json``: ``K_*`` (px), ``dist_*`` (OpenCV order), ``R``, ``T`` (mm, x_right =
    R x_left + T), ``image_size`` (w, h) px of both cameras, ``model`` ("pinhole" or "fisheye")."""

    image_size: tuple[int, int]
    model: str
    K_left: np.ndarray
    dist_left: np.ndarray
    K_right: np.ndarray
    dist_right: np.ndarray
    R: np.ndarray
    T: np.ndarray

    def K(self, camera: str) -> np.ndarray:
        return self.K_left if camera == "left" else self.K_right

    def dist(self, camera: str) -> np.ndarray:
        return self.dist_left if camera == "left" else self.dist_right

    @property
    def right_centre_mm(self) -> np.ndarray:
        """The right camera's centre in the left camera frame (mm): -R^T T."""
        return -self.R.T @ self.T

    @cached_property
    def rectification(self) -> Rectification:
        """Rectification keeping every valid pixel (alpha = 0: no black borders) at the same image size."""
        args = (self.K_left, self.dist_left, self.K_right, self.dist_right, self.image_size, self.R, self.T.reshape(3, 1))
        if self.model == "fisheye":
            R1, R2, P1, P2, Q = cv2.fisheye.stereoRectify(*args, flags=cv2.CALIB_ZERO_DISPARITY, balance=0.0)
        else:
            R1, R2, P1, P2, Q, _, _ = cv2.stereoRectify(*args, flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
        return Rectification(R1, R2, P1, P2, Q, self.image_size)

    def normalised(self, uv: np.ndarray, camera: str) -> np.ndarray:
        """Undistorted normalised coordinates (x/z, y/z) in ``camera``'s own frame of recorded pixels (N, 2)."""
        return self._undistort(uv, camera, None, None)

    def rectified(self, uv: np.ndarray, camera: str) -> np.ndarray:
        """Rectified pixel coordinates (N, 2) of recorded pixels ``uv`` (N, 2) of ``camera``."""
        r = self.rectification
        R, P = (r.R1, r.P1) if camera == "left" else (r.R2, r.P2)
        return self._undistort(uv, camera, R, P)

    @cached_property
    def rectification_maps(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """``cv2.remap`` maps (float32, h x w) per camera: rectified image = remap(recorded, *maps[camera])."""
        r, out = self.rectification, {}
        for cam, R, P in (("left", r.R1, r.P1), ("right", r.R2, r.P2)):
            init = cv2.fisheye.initUndistortRectifyMap if self.model == "fisheye" else cv2.initUndistortRectifyMap
            out[cam] = init(self.K(cam), self.dist(cam), R, P, self.image_size, cv2.CV_32FC1)
        return out

    def _undistort(self, uv: np.ndarray, camera: str, R: np.ndarray | None, P: np.ndarray | None) -> np.ndarray:
        p = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        if len(p) == 0:
            return np.zeros((0, 2))
        undistort = cv2.fisheye.undistortPoints if self.model == "fisheye" else cv2.undistortPoints
        return undistort(p, self.K(camera), self.dist(camera), R=R, P=P, criteria=_CRITERIA).reshape(-1, 2)


def calibration_from_dict(data: dict, source: Path | str = "calibration") -> StereoCalibration:
    """Check and convert a ``calibration.json`` dictionary; every problem raises ``PerceptionInputError``."""
    if not isinstance(data, dict):
        raise PerceptionInputError(source, "not a JSON object", "write the keys of DESIGN.md section 4")
    need = ("image_size", "K_left", "dist_left", "K_right", "dist_right", "R", "T")
    missing = [k for k in need if k not in data]
    if missing:
        raise PerceptionInputError(source, f"missing key(s) {', '.join(missing)}",
                                   "write every key that OpenCV's stereoCalibrate returns (DESIGN.md section 4)")
    model = data.get("model", "pinhole")
    if model not in MODELS:
        raise PerceptionInputError(source, f"model {model!r} is not one of {', '.join(MODELS)}", "fix 'model'")
    if data.get("units", "mm") != "mm":
        raise PerceptionInputError(source, f"units {data['units']!r}", "give T in millimetres (units = 'mm')")
    arrays = {}
    for key in need[1:]:
        try:
            arrays[key] = np.asarray(data[key], dtype=np.float64)
        except (TypeError, ValueError):
            raise PerceptionInputError(source, f"{key} is not numeric", f"fix '{key}'") from None
        if not np.all(np.isfinite(arrays[key])):
            raise PerceptionInputError(source, f"{key} has non-finite values", f"fix '{key}'")
        if key == "T" and arrays[key].shape in ((3, 1), (1, 3)):  # OpenCV's stereoCalibrate returns T as 3 x 1
            arrays[key] = arrays[key].ravel()
        if key in _SHAPES and arrays[key].shape != _SHAPES[key]:
            raise PerceptionInputError(source, f"{key} has shape {arrays[key].shape}, not {_SHAPES[key]}", f"fix '{key}'")
        if key.startswith("dist"):
            arrays[key] = arrays[key].ravel()
            if arrays[key].size not in _DIST_LENGTHS[model]:
                raise PerceptionInputError(source, f"{key} has {arrays[key].size} coefficients",
                                           f"the {model} model takes {' or '.join(map(str, _DIST_LENGTHS[model]))}")
    size = data["image_size"]
    if not (isinstance(size, list | tuple) and len(size) == 2 and all(isinstance(s, int) and s > 0 for s in size)):
        raise PerceptionInputError(source, f"image_size {size!r} is not [width, height] in pixels", "fix 'image_size'")
    return StereoCalibration((int(size[0]), int(size[1])), model, **arrays)


def load_calibration(path: Path | str) -> StereoCalibration:
    """Read ``calibration.json`` (a file, or a dataset folder holding one)."""
    path = Path(path)
    if path.is_dir():
        path = path / "calibration.json"
    if not path.is_file():
        raise PerceptionInputError(path, "no such file", "pass a calibration.json or a dataset folder")
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise PerceptionInputError(path, f"not readable JSON ({e})", "pass a calibration.json") from None
    return calibration_from_dict(data, path)


def check_image_size(calib: StereoCalibration, size: tuple[int, int], source: Path | str) -> None:
    """Raise ``PerceptionInputError`` when an image's (w, h) is not the calibrated one."""
    if tuple(size) != calib.image_size:
        raise PerceptionInputError(source, f"image is {size[0]}x{size[1]} px, the calibration is for "
                                   f"{calib.image_size[0]}x{calib.image_size[1]}",
                                   "calibrate at this image size or resize the images")
