"""Exact light paths from points inside the gel to a camera centre, through the planar layers between.

In the left camera's frame (mm) the gel's bonded face is the plane z = z_bond and the backing fills
z_back <= z <= z_bond (both planar, they never move); a camera centre C lies at z < z_back. The path from
a point P in the gel (z > z_bond) to C crosses the planes z = z_bond (gel -> backing) and z = z_back
(backing -> air). Every interface is perpendicular to z, so by Snell's law (equivalently Fermat's
principle) the path lies in the vertical plane through P and C and s = n sin(theta) is the same in
every layer; the horizontal distance it travels,

    rho(s) = sum_layers h_i (s / n_i) / sqrt(1 - (s / n_i)^2),

grows monotonically from 0 at s = 0 to infinity as s -> 1 (the air layer going grazing). So for every
horizontal distance |P - C|_xy there is exactly one s in [0, 1), found here by bisection to double
precision: leaving a flat stack towards a camera there is no total internal reflection. (Paths that
would leave the gel through its sides or deformed contact face are dealt with in ``labels.markers``.)
The camera's rotation does not matter for the path, only for the direction in the camera's frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def solve_exit_sine(rho: np.ndarray, layers: list[tuple[np.ndarray, float]], iterations: int = 64) -> np.ndarray:
    """s in [0, 1) with sum_i h_i tan(theta_i) = rho, sin(theta_i) = s / n_i, for layers (h_i mm, n_i >= 1)."""
    rho = np.asarray(rho, dtype=np.float64)
    lo, hi = np.zeros_like(rho), np.ones_like(rho)
    for _ in range(iterations):
        s = 0.5 * (lo + hi)
        travel = sum(h * (s / n) / np.sqrt(1.0 - (s / n) ** 2) for h, n in layers)
        too_far = travel > rho
        hi = np.where(too_far, s, hi)
        lo = np.where(too_far, lo, s)
    return 0.5 * (lo + hi)


@dataclass(frozen=True)
class PlanarStack:
    """The flat layers in front of the cameras: backing z in [z_back, z_bond] (index n_backing), gel above
    z_bond (index n_gel), air below z_back; left camera frame, mm."""

    z_back: float
    z_bond: float
    n_backing: float
    n_gel: float


@dataclass(frozen=True)
class RefractedPaths:
    directions_left: np.ndarray  # (K, 3) unit direction of each path leaving the camera (left frame)
    exit_sine: np.ndarray  # (K,) s = n sin(theta), the same in every layer
    at_bond: np.ndarray  # (K, 3) where the path crosses z = z_bond
    at_back: np.ndarray  # (K, 3) where the path crosses z = z_back


def refracted_paths(stack: PlanarStack, camera_centre: np.ndarray, points: np.ndarray) -> RefractedPaths:
    """Exact paths from ``points`` (K, 3; z > z_bond) to ``camera_centre`` (3,; z < z_back), left frame."""
    C = np.asarray(camera_centre, np.float64)
    P = np.atleast_2d(np.asarray(points, np.float64))
    if C[2] >= stack.z_back or np.any(P[:, 2] < stack.z_bond):
        raise ValueError("the camera must be in front of the backing and the points inside the gel")
    d_xy = P[:, :2] - C[:2]
    rho = np.linalg.norm(d_xy, axis=1)
    e = np.divide(d_xy, rho[:, None], out=np.zeros_like(d_xy), where=rho[:, None] > 0)
    ones = np.ones(len(P))
    h_air, h_back = (stack.z_back - C[2]) * ones, (stack.z_bond - stack.z_back) * ones
    layers = [(h_air, 1.0), (h_back, stack.n_backing), (P[:, 2] - stack.z_bond, stack.n_gel)]
    s = solve_exit_sine(rho, layers)

    def travel(h, n):
        return (h * (s / n) / np.sqrt(1.0 - (s / n) ** 2))[:, None] * e

    at_back = np.column_stack([C[:2] + travel(h_air, 1.0), stack.z_back * ones])
    at_bond = np.column_stack([at_back[:, :2] + travel(h_back, stack.n_backing), stack.z_bond * ones])
    dirs = np.column_stack([e * s[:, None], np.sqrt(1.0 - s**2)])
    return RefractedPaths(dirs, s, at_bond, at_back)
