"""The classical baseline: colour/intensity thresholding plus blob detection on the UV image (OpenCV),
with intensity-weighted sub-pixel centres.

Steps: the marker channel (green by default: the pigment's emission) minus the mean of the other two
(removes white-light leak, which is grey); a threshold at ``threshold_fraction`` of the image's bright
level (its 99.9th percentile), so exposure does not matter; OpenCV's SimpleBlobDetector on that mask
(``blobColor = 255``: it looks for dark blobs by default) with area and circularity filters; then each
blob's centre refined by the intensity centroid (``refine.intensity_centroids``). A blob's score is its peak
over the bright level: it ranks blobs, it is not a confidence (``Detections.confident_from`` is 0: the tracker
takes every blob as a confident detection).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from transtac_sim.perception.detection import Detections
from transtac_sim.perception.detection.refine import intensity_centroids

CHANNELS = {"blue": 0, "green": 1, "red": 2}


@dataclass(frozen=True)
class BlobParams:
    channel: str = "green"
    threshold_fraction: float = 0.3
    min_area_px: float = 4.0
    max_area_px: float = 400.0
    min_circularity: float = 0.5


def marker_response(image_bgr: np.ndarray, channel: str = "green") -> np.ndarray:
    """float32 (H, W): the marker channel minus the mean of the other two, clipped at 0."""
    c = CHANNELS[channel]
    img = image_bgr.astype(np.float32)
    others = [i for i in range(3) if i != c]
    return np.clip(img[:, :, c] - 0.5 * (img[:, :, others[0]] + img[:, :, others[1]]), 0.0, None)


def detect_blobs(image_bgr: np.ndarray, params: BlobParams = BlobParams()) -> Detections:
    t0 = time.perf_counter()
    resp = marker_response(image_bgr, params.channel)
    bright = max(float(np.percentile(resp, 99.9)), 4.0)
    mask = (resp >= params.threshold_fraction * bright).astype(np.uint8) * 255
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor, p.blobColor = True, 255
    p.minThreshold, p.maxThreshold, p.thresholdStep = 127, 129, 1
    p.filterByArea, p.minArea, p.maxArea = True, params.min_area_px, params.max_area_px
    p.filterByCircularity, p.minCircularity = True, params.min_circularity
    p.filterByInertia = p.filterByConvexity = False
    p.minDistBetweenBlobs = 2.0
    keypoints = cv2.SimpleBlobDetector_create(p).detect(mask)
    t1 = time.perf_counter()
    if not keypoints:
        return Detections(np.zeros((0, 2)), np.zeros(0), np.zeros((0, 2)), {"detect": t1 - t0, "refine": 0.0},
                          confident_from=0.0)
    uv = np.array([k.pt for k in keypoints], dtype=np.float64)
    diameter = np.array([k.size for k in keypoints], dtype=np.float64)
    uv = intensity_centroids(resp, uv, int(np.clip(np.median(diameter) * 0.75 + 1.5, 3, 12)))
    peak = np.array([resp[int(round(v)), int(round(u))] for u, v in np.clip(uv, 0, [resp.shape[1] - 1, resp.shape[0] - 1])])
    score = np.clip(peak / bright, 0.0, 1.0)
    size = np.repeat(diameter[:, None], 2, axis=1)
    return Detections(uv, score, size, {"detect": t1 - t0, "refine": time.perf_counter() - t1}, confident_from=0.0)
