"""The optical-flow baseline of the paper's comparison: Farneback dense flow carries each track's position
from one frame's image to the next; the new frame's detections are then assigned to the carried positions
(Hungarian on the distance, within ``gate_px``), and unassigned detections start new tracks."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

from transtac_sim.perception.detection import Detections
from transtac_sim.perception.detection.blob import marker_response
from transtac_sim.perception.tracking import TrackResult


def _flow_image(image_bgr: np.ndarray) -> np.ndarray:
    resp = marker_response(image_bgr)
    return cv2.normalize(resp, None, 0, 255, cv2.NORM_MINMAX).astype(np.uint8)


def track_flow(frames: list[Detections], images: list[np.ndarray], gate_px: float = 4.0) -> TrackResult:
    """Track markers over ``frames`` with the flow between consecutive ``images`` (8-bit BGR, same order)."""
    uvs, ids = [], []
    positions: dict[int, np.ndarray] = {}  # track id -> last known (carried) position
    next_id = 0
    prev = None
    for det, image in zip(frames, images, strict=True):
        gray = _flow_image(image)
        frame_ids = np.full(len(det), -1, dtype=np.int64)
        if prev is not None and positions:
            flow = cv2.calcOpticalFlowFarneback(prev, gray, None, 0.5, 3, 15, 3, 5, 1.2, 0)
            h, w = gray.shape
            for t, p in positions.items():
                x, y = int(np.clip(round(p[0]), 0, w - 1)), int(np.clip(round(p[1]), 0, h - 1))
                positions[t] = p + flow[y, x]
            keys = list(positions)
            if len(det):
                d = cdist(np.array([positions[k] for k in keys]), det.uv)
                r, c = linear_sum_assignment(np.where(d <= gate_px, d, 1e6))
                for i, j in zip(r, c, strict=True):
                    if d[i, j] <= gate_px:
                        frame_ids[j] = keys[i]
        for j in np.nonzero(frame_ids < 0)[0]:
            frame_ids[j] = next_id
            next_id += 1
        for j, t in enumerate(frame_ids):
            positions[int(t)] = det.uv[j].astype(np.float64)
        uvs.append(det.uv)
        ids.append(frame_ids)
        prev = gray
    return TrackResult(uvs, ids)
