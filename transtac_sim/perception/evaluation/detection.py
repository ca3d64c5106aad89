"""Detection against exact marker centres: one-to-one matching within a radius, precision, recall, F1
and localisation error.

A detection and a true marker match when the optimal assignment (Hungarian, on the distance in px) pairs
them and they are at most ``radius_px`` apart. precision = matches / detections, recall = matches / true
markers, F1 = 2 P R / (P + R); localisation error = distance of the matched pairs (px).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist


def match_points(pred: np.ndarray, truth: np.ndarray, radius_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Indices (pred_i, truth_j) of the matched pairs and their distances (px)."""
    if len(pred) == 0 or len(truth) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    d = cdist(pred, truth)
    big = 1e6
    i, j = linear_sum_assignment(np.where(d <= radius_px, d, big))
    keep = d[i, j] <= radius_px
    return i[keep], j[keep], d[i[keep], j[keep]]


@dataclass
class DetectionTally:
    """Counts summed over images; ``errors_px`` of the matches at the largest radius."""

    radii_px: tuple[float, ...] = (1.0, 2.0)
    detections: int = 0
    truths: int = 0

    def __post_init__(self) -> None:
        self.matches = {r: 0 for r in self.radii_px}
        self.errors: list[np.ndarray] = []

    def add(self, pred: np.ndarray, truth: np.ndarray) -> None:
        self.detections += len(pred)
        self.truths += len(truth)
        for r in self.radii_px:
            _, _, d = match_points(pred, truth, r)
            self.matches[r] += len(d)
            if r == max(self.radii_px):
                self.errors.append(d)

    def summary(self) -> dict:
        out = {"images_truths": self.truths, "detections": self.detections}
        for r in self.radii_px:
            m = self.matches[r]
            p = m / self.detections if self.detections else 0.0
            rc = m / self.truths if self.truths else 0.0
            out[f"precision@{r:g}px"] = p
            out[f"recall@{r:g}px"] = rc
            out[f"f1@{r:g}px"] = 2 * p * rc / (p + rc) if p + rc else 0.0
        err = np.concatenate(self.errors) if self.errors else np.zeros(0)
        out["error_median_px"] = float(np.median(err)) if len(err) else float("nan")
        out["error_p95_px"] = float(np.percentile(err, 95)) if len(err) else float("nan")
        return out
