"""3D marker positions (mm, left camera OpenCV frame: x right, y down, z forward) from matched pixels.

Linear (``triangulate_linear``): the pinhole model. Undistorted normalised points x_l, x_r
(``StereoCalibration.normalised``) and the projections P_l = [I | 0], P_r = [R | T] go to
``cv2.triangulatePoints`` (DLT). Through the TransTac's backing and gel the rays bend, so a pinhole
intersection is off by a fraction of a millimetre (and true pairs do not share a rectified row).

Refraction-aware (``triangulate_refracted``): each camera ray (centre C: 0 for the left camera,
-R^T T for the right; direction R_cam^T (x, y, 1) normalised) is traced through a ``FlatStack``:
air | backing (thickness h, index n_b) | gel (index n_g, beyond the bonded face). At each interface of
unit normal n (pointing away from the cameras) a unit direction d with c = d . n refracts by Snell's law
in vector form, eta = n_1 / n_2:

    d' = eta d + (sqrt(1 - eta^2 (1 - c^2)) - eta c) n.

Going into denser media (eta < 1) there is no total internal reflection. The two rays in the gel,
X_l + s d_l and X_r + t d_r, are intersected in the least-squares sense: the midpoint of their common
perpendicular (s, t solve the 2x2 normal equations). The gel's contact surface does not bend these rays
(the markers are inside the gel), so the gel's thickness is not needed.

The stack of a hardware model (``hardware_models/*.toml``) whose cameras look straight at the backing
(as in ``transtac.toml``): ``point_mm`` = [0, 0, cameras.distance_to_backing_mm], ``normal`` = [0, 0, 1],
``backing_thickness_mm`` = backing.thickness_mm, ``n_backing`` and ``n_gel`` = the ``refractive_index``
of ``materials/<backing.material>.toml`` and ``materials/<gel.material>.toml``. As a JSON file
(``load_flat_stack``), for the default model:

    {"point_mm": [0, 0, 15.0], "normal": [0, 0, 1], "backing_thickness_mm": 2.0,
     "n_backing": 1.49, "n_gel": 1.41, "gel_thickness_mm": 5.0}

(``gel_thickness_mm`` is optional: only points beyond the gel need it, ``stereo.anchors``.)

``scripts/bench_matching.py --write-stack FILE`` writes it from the simulator's sensor. On a real build,
measure the camera-to-backing distance along the left camera's axis (a tilted backing: its normal in
the left camera's frame, e.g. from a board laid on the backing during calibration).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.perception.stereo.calibration import StereoCalibration


@dataclass(frozen=True, eq=False)
class FlatStack:
    """The flat layers in front of the cameras, in the left camera frame (mm).

    point_mm: a point on the backing's face towards the cameras; normal: unit normal of the backing,
    pointing away from the cameras; backing_thickness_mm: h; n_backing, n_gel, n_air: refractive indices;
    gel_thickness_mm: the gel's, bonded face to contact surface (None: not given).
    """

    point_mm: np.ndarray
    normal: np.ndarray
    backing_thickness_mm: float
    n_backing: float
    n_gel: float
    n_air: float = 1.0
    gel_thickness_mm: float | None = None


def flat_stack_from_dict(data: dict, source: Path | str = "stack") -> FlatStack:
    """Check and convert a flat stack's JSON dictionary (module docstring); problems raise
    ``PerceptionInputError``."""
    keys = ("point_mm", "normal", "backing_thickness_mm", "n_backing", "n_gel")
    missing = [k for k in keys if k not in data] if isinstance(data, dict) else list(keys)
    if missing:
        raise PerceptionInputError(source, f"missing key(s) {', '.join(missing)}",
                                   "see transtac_sim/perception/stereo/triangulation.py for the format")
    try:
        point, normal = np.asarray(data["point_mm"], float), np.asarray(data["normal"], float)
        h, nb, ng = (float(data[k]) for k in ("backing_thickness_mm", "n_backing", "n_gel"))
        na = float(data.get("n_air", 1.0))
        gel = None if data.get("gel_thickness_mm") is None else float(data["gel_thickness_mm"])
    except (TypeError, ValueError):
        raise PerceptionInputError(source, "a value is not numeric", "give numbers in mm and plain indices") from None
    if point.shape != (3,) or normal.shape != (3,) or not np.linalg.norm(normal) > 0:
        raise PerceptionInputError(source, "point_mm and normal must be 3-vectors (normal non-zero)", "fix them")
    if h <= 0 or (gel is not None and gel <= 0) or min(nb, ng, na) < 1.0:
        raise PerceptionInputError(source, "thicknesses must be > 0 and refractive indices >= 1", "fix them")
    normal = normal / np.linalg.norm(normal)
    if normal @ point <= 0:
        raise PerceptionInputError(source, "the backing must lie in front of the left camera along its normal",
                                   "give the normal pointing away from the cameras")
    return FlatStack(point, normal, h, nb, ng, na, gel)


def load_flat_stack(path: Path | str) -> FlatStack:
    """Read a flat stack's JSON file (module docstring)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise PerceptionInputError(path, f"not a readable JSON file ({e})", "pass the stack's JSON file") from None
    return flat_stack_from_dict(data, path)


def triangulate_linear(calib: StereoCalibration, left_uv: np.ndarray, right_uv: np.ndarray) -> np.ndarray:
    """Points (K, 3) mm, left camera frame, of matched recorded pixels ``left_uv``, ``right_uv`` (K, 2)."""
    xl, xr = calib.normalised(left_uv, "left"), calib.normalised(right_uv, "right")
    if len(xl) == 0:
        return np.zeros((0, 3))
    P_r = np.hstack([calib.R, calib.T.reshape(3, 1)])
    X = cv2.triangulatePoints(np.eye(3, 4), P_r, xl.T.copy(), xr.T.copy())
    return (X[:3] / X[3]).T


def refract(d: np.ndarray, normal: np.ndarray, eta: float) -> np.ndarray:
    """Unit directions (K, 3) after crossing an interface of unit ``normal`` (along the propagation) from
    index n_1 to n_2, eta = n_1 / n_2 <= 1 (module docstring)."""
    c = d @ normal
    return eta * d + (np.sqrt(1.0 - eta**2 * (1.0 - c**2)) - eta * c)[:, None] * normal


def rays_in_gel(stack: FlatStack, centre: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where rays from ``centre`` (3,) (or one per ray, (K, 3)) along unit ``directions`` (K, 3) (left frame)
    enter the gel (K, 3), mm, and their unit directions there (K, 3)."""
    n = stack.normal
    t = ((stack.point_mm - centre) @ n) / (directions @ n)
    at_back = centre + t[:, None] * directions
    d = refract(directions, n, stack.n_air / stack.n_backing)
    at_bond = at_back + (stack.backing_thickness_mm / (d @ n))[:, None] * d
    return at_bond, refract(d, n, stack.n_backing / stack.n_gel)


def _closest_points_midpoint(p: np.ndarray, u: np.ndarray, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Midpoints (K, 3) of the common perpendiculars of lines p + s u and q + t v (unit u, v)."""
    w = p - q
    b, d, e = np.sum(u * v, 1), np.sum(u * w, 1), np.sum(v * w, 1)
    den = np.maximum(1.0 - b**2, 1e-12)
    s, t = (b * e - d) / den, (e - b * d) / den
    return 0.5 * (p + s[:, None] * u + q + t[:, None] * v)


def stereo_rays(calib: StereoCalibration, left_uv: np.ndarray, right_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres and unit directions (2K, 3) in the left frame of the rays through recorded pixels
    ``left_uv`` then ``right_uv`` (K, 2 each), before any refraction."""
    k = len(left_uv)
    xy = np.concatenate([calib.normalised(left_uv, "left"), calib.normalised(right_uv, "right")])
    d = np.column_stack([xy, np.ones(len(xy))])
    d[k:] = d[k:] @ calib.R  # R^T applied to each row: right camera -> left frame
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    centres = np.zeros_like(d)
    centres[k:] = calib.right_centre_mm
    return centres, d


def triangulate_refracted(calib: StereoCalibration, stack: FlatStack, left_uv: np.ndarray,
                          right_uv: np.ndarray) -> np.ndarray:
    """Points (K, 3) mm, left camera frame, of matched recorded pixels (K, 2) through ``stack``."""
    k = len(left_uv)
    if k == 0:
        return np.zeros((0, 3))
    p, d = rays_in_gel(stack, *stereo_rays(calib, left_uv, right_uv))  # both cameras' rays at once
    return _closest_points_midpoint(p[:k], d[:k], p[k:], d[k:])
