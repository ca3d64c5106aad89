"""ByteTrack on marker detections, through the ``trackers`` package's ByteTrackTracker.

Markers are a few pixels wide, so box overlap (IoU) stops associating a marker with its track once it moves
about its own size between frames. The association here is a centre-distance similarity instead,
    s(track, detection) = max(0, 1 - |c_track - c_det| / gate_px),
with c_track the Kalman-predicted centre; a pair is associated when s >= ``min_similarity``. Box overlap
on boxes enlarged ``box_scale`` times (default 3x) tolerates more motion still (it holds up to 12-14 px per
frame against 10 px for the 12 px centre gate: ``scripts/bench_tracking.py``) and is the default; the
detector's own boxes (plain IoU) fail from 6 px per frame, about a marker's size.

The package's tracker gives a new track its id only when it is seen a second time; the detection that
started it is then given that id too (the original ByteTrack activates every track of the first frame at
once), so a marker is tracked from the first frame it appears in.
"""

from __future__ import annotations

import numpy as np

from transtac_sim.perception.detection import Detections
from transtac_sim.perception.tracking import TrackResult


def _centre_similarity_class():
    from trackers.utils.iou import BaseIoU

    class CentreDistance(BaseIoU):
        def __init__(self, gate_px: float) -> None:
            self.gate_px = gate_px

        def _compute(self, boxes_1: np.ndarray, boxes_2: np.ndarray) -> np.ndarray:
            c1 = (boxes_1[:, :2] + boxes_1[:, 2:]) / 2
            c2 = (boxes_2[:, :2] + boxes_2[:, 2:]) / 2
            d = np.linalg.norm(c1[:, None, :] - c2[None, :, :], axis=2)
            return np.clip(1.0 - d / self.gate_px, 0.0, None)

    return CentreDistance


def track_bytetrack(frames: list[Detections], association: str = "iou_enlarged", gate_px: float = 12.0,
                    box_scale: float = 3.0, min_similarity: float = 0.1,
                    score_split: float | None = None) -> TrackResult:
    """Track markers over ``frames`` (one Detections per frame, in order). ``association``: ``iou_enlarged``
    (default: boxes ``box_scale`` times larger), ``centre`` (centre distance) or ``iou`` (the detector's boxes).
    ``score_split``: ByteTrack's split between high-score detections (associated first; the only ones that start a
    track) and low-score ones (only continue a track); by default the detector's ``Detections.confident_from``
    (the lowest score it reports: every detection can start a track)."""
    import supervision as sv
    from trackers import ByteTrackTracker
    from trackers.utils.iou import IoU

    if association not in ("centre", "iou", "iou_enlarged"):
        raise ValueError(f"unknown association {association!r} (centre, iou or iou_enlarged)")
    sim = _centre_similarity_class()(gate_px) if association == "centre" else IoU()
    if score_split is None:
        score_split = min((d.confident_from for d in frames), default=0.5)
    tracker = ByteTrackTracker(lost_track_buffer=30, frame_rate=30.0, track_activation_threshold=score_split,
                               minimum_consecutive_frames=1, minimum_iou_threshold=min_similarity,
                               high_conf_det_threshold=score_split, iou=sim)
    uvs, ids = [], []
    pending: dict[int, tuple[object, int, int]] = {}  # new tracklet -> (tracklet, frame, detection index)
    alive: set[int] = set()  # the tracklets (ids) after the last update
    for f, det in enumerate(frames):
        n = len(det)
        boxes = det.boxes_xyxy(min_size_px=3.0)
        if association == "iou_enlarged":
            half = (boxes[:, 2:] - boxes[:, :2]) * box_scale / 2
            boxes = np.hstack([det.uv - half, det.uv + half])
        sv_det = sv.Detections(xyxy=boxes.reshape(-1, 4).astype(np.float32), confidence=det.score.astype(np.float32),
                               data={"index": np.arange(n)})
        before = alive
        res = tracker.update(sv_det)
        alive = {id(t) for t in tracker.tracks}
        frame_ids = np.full(n, -1, dtype=np.int64)
        if len(res):  # an empty result carries no data columns
            frame_ids[np.asarray(res.data["index"], dtype=int)] = np.asarray(res.tracker_id, dtype=np.int64)
        uvs.append(det.uv)
        ids.append(frame_ids)
        new = [t for t in tracker.tracks if id(t) not in before] if n else []
        if new:  # tracks started in this frame: remember which detection (nearest their centre) started them
            box = np.array([t.get_state_bbox() for t in new])
            js = np.argmin(np.linalg.norm(det.uv[None] - ((box[:, :2] + box[:, 2:]) / 2)[:, None], axis=2), axis=1)
            pending.update((id(t), (t, f, int(j))) for t, j in zip(new, js, strict=True))
        for key, (t, f0, j) in list(pending.items()):
            if t.tracker_id != -1:
                if ids[f0][j] == -1:
                    ids[f0][j] = t.tracker_id
                del pending[key]
            elif id(t) not in alive:
                del pending[key]
    return TrackResult(uvs, ids)
