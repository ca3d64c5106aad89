"""Stereo matching of marker detections: which left point is which right point.

Every matcher has the signature ``matcher(left_uv, right_uv, calib, params) -> pairs``: recorded
(distorted) pixels of the left (N, 2) and right (M, 2) detections, the pair's ``StereoCalibration`` and
``MatchParams``; ``pairs`` is an int array (K, 2) of (i, j) indices into the two lists, sorted by i.

All work on rectified coordinates (``calibration``): a left point (x_l, y_l) and a right point (x_r, y_r)
are candidates when they pass the epipolar gate |y_r - y_l| <= tau_epi and their disparity
d = x_l - x_r lies in the plausible range [d_ref - w, d_ref + w]. Unless given, d_ref is the mode of
the disparities of all pairs in the y gate (a histogram with ``disparity_bin_px`` bins): the markers lie
in a thin layer, so true pairs share nearly one disparity while wrong pairs spread over the image width.

- ``epipolar_nn``: each left point takes the candidate whose disparity is nearest d_ref (nearest in the
  disparity direction); a right point may be taken more than once.
- ``hungarian``: one-to-one assignment (``scipy.optimize.linear_sum_assignment``) minimising
  (dy / tau_epi)^2 + ((d - d_ref) / w)^2 over the candidates; pairs outside the gate are never assigned.
- ``delaunay`` (prior-guided Delaunay, ``delaunay.py``): epipolar NN initialisation, anchor triangles of
  the two views' Delaunay triangulations, propagation to adjacent triangles with geometric checks.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from transtac_sim.perception.stereo.calibration import StereoCalibration


@dataclass(frozen=True)
class MatchParams:
    """Matching tolerances (rectified px; the defaults are for the TransTac at 640x480: markers >= ~22 px
    apart, disparities 150-165 px; scale the pixel values with the image width).

    tau_epi_px: epipolar gate on |y_r - y_l|; refraction through the backing and gel offsets true pairs
      by up to ~5 px (DESIGN.md section 5): 3 px keeps ~82 % of them for the anchors of the Delaunay
      matcher, which finds the rest by propagation; the NN and Hungarian baselines need ~6 px.
    disparity_px: the expected disparity d_ref; None estimates it per frame (module docstring).
    disparity_halfwidth_px: w, the plausible range is d_ref +- w.
    disparity_bin_px: histogram bin of the d_ref estimate.
    desc_tol: largest difference of corresponding normalised edge lengths (edge / perimeter) of two
      matched triangles (Delaunay).
    prop_tol_px: (x, y) tolerance of a propagated match around the position that its matched neighbours
      predict (Delaunay).
    """

    tau_epi_px: float = 3.0
    disparity_px: float | None = None
    disparity_halfwidth_px: float = 20.0
    disparity_bin_px: float = 4.0
    desc_tol: float = 0.05
    prop_tol_px: tuple[float, float] = (6.0, 2.5)


Matcher = Callable[[np.ndarray, np.ndarray, StereoCalibration, MatchParams], np.ndarray]


@dataclass(frozen=True)
class Candidates:
    """Rectified points of both views and the (N, M) arrays of their y offsets and disparities (px)."""

    left: np.ndarray  # (N, 2)
    right: np.ndarray  # (M, 2)
    dy: np.ndarray  # (N, M) y_r - y_l
    disparity: np.ndarray  # (N, M) x_l - x_r
    d_ref: float
    gate: np.ndarray  # (N, M) bool: epipolar gate and plausible disparity


def no_pairs() -> np.ndarray:
    return np.zeros((0, 2), dtype=np.int64)


def _disparity_mode(d: np.ndarray, b: float) -> float:
    """The mode (px) of the disparities ``d`` of the pairs within the epipolar gate (histogram bins ``b`` px,
    smoothed; the median of the disparities near the peak), NaN when there are none."""
    if d.size == 0:
        return float("nan")
    d = np.sort(d)
    edges = d[0] - b + b * np.arange(int(np.ceil((d[-1] - d[0]) / b)) + 4)  # >= 3 bins, one empty each end
    # np.histogram(d, edges) of sorted d (the last bin closed): counts between the edges' insertion points
    counts = np.diff(np.concatenate([np.searchsorted(d, edges[:-1], "left"), np.searchsorted(d, edges[-1:], "right")]))
    smooth = np.convolve(counts, [1, 2, 1], mode="same")  # a peak split over two bins still wins
    k = int(np.argmax(smooth))
    near = d[np.abs(d - 0.5 * (edges[k] + edges[k + 1])) <= 1.5 * b]  # sorted: its median is the middle
    n = len(near)
    if n == 0:
        return float("nan")
    return float(near[n // 2]) if n % 2 else float((near[n // 2 - 1] + near[n // 2]) / 2)


def candidates(left_uv: np.ndarray, right_uv: np.ndarray, calib: StereoCalibration,
               params: MatchParams) -> Candidates:
    """Rectify both views and gate every pair (module docstring)."""
    L, R = calib.rectified(left_uv, "left"), calib.rectified(right_uv, "right")
    dy = R[None, :, 1] - L[:, None, 1]
    disp = L[:, None, 0] - R[None, :, 0]
    tmp = np.abs(dy)
    in_y = tmp <= params.tau_epi_px
    d_ref = params.disparity_px if params.disparity_px is not None else _disparity_mode(disp[in_y], params.disparity_bin_px)
    np.abs(np.subtract(disp, d_ref, out=tmp), out=tmp)
    gate = np.less_equal(tmp, params.disparity_halfwidth_px, out=np.empty(tmp.shape, bool))
    gate &= in_y
    return Candidates(L, R, dy, disp, d_ref, gate)


def nn_from_candidates(c: Candidates) -> np.ndarray:
    """(N,) index of each left point's epipolar nearest neighbour, -1 where no candidate passes the gate."""
    if c.gate.size == 0:
        return np.full(len(c.left), -1)
    cost = np.where(c.gate, np.abs(c.disparity - c.d_ref), np.inf)
    j = np.argmin(cost, axis=1)
    return np.where(np.isfinite(cost[np.arange(len(j)), j]), j, -1)


def match_epipolar_nn(left_uv: np.ndarray, right_uv: np.ndarray, calib: StereoCalibration,
                      params: MatchParams = MatchParams()) -> np.ndarray:
    """Epipolar nearest neighbour (module docstring): pairs (K, 2) of left and right indices."""
    nn = nn_from_candidates(candidates(left_uv, right_uv, calib, params))
    i = np.flatnonzero(nn >= 0)
    return np.column_stack([i, nn[i]]).astype(np.int64)


def match_hungarian(left_uv: np.ndarray, right_uv: np.ndarray, calib: StereoCalibration,
                    params: MatchParams = MatchParams()) -> np.ndarray:
    """Gated one-to-one assignment (module docstring): pairs (K, 2) of left and right indices."""
    c = candidates(left_uv, right_uv, calib, params)
    if not c.gate.any():
        return no_pairs()
    cost = (c.dy / params.tau_epi_px) ** 2 + ((c.disparity - c.d_ref) / params.disparity_halfwidth_px) ** 2
    forbidden = 1e6  # more than all gated costs together (each <= 2): the most gated pairs come first
    i, j = linear_sum_assignment(np.where(c.gate, cost, forbidden))
    keep = c.gate[i, j]
    return np.column_stack([i[keep], j[keep]]).astype(np.int64)
