"""Marker detectors: the classical blob baseline (``blob``) and the learned CenterNet-style network
(``network``, run by ``runtime``). Both return :class:`Detections` in recorded-image pixels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Detections:
    uv: np.ndarray  # (N, 2) marker centres, px (OpenCV convention)
    score: np.ndarray  # (N,) in [0, 1]: the learned detector's confidence, the blob baseline's brightness ratio
    size: np.ndarray  # (N, 2) box width, height, px
    seconds: dict[str, float] = field(default_factory=dict)  # pre-processing, network, decoding
    #: the score from which a detection is a confident one (ByteTrack's high-score detections: associated first, and
    #: the only ones that start a track). The detectors set it to the lowest score they report: the learned
    #: detector's threshold (0.4 by default), so every detection it reports can start a track (fewer missed markers
    #: on the held-out sequences than ByteTrack's 0.5: BENCHMARKS.md ``tracking``), and 0 for the blob baseline,
    #: whose scores rank blobs by brightness. 0.5 (ByteTrack's split) where nothing sets it.
    confident_from: float = 0.5

    def __len__(self) -> int:
        return len(self.uv)

    def boxes_xyxy(self, min_size_px: float = 0.0) -> np.ndarray:
        half = np.maximum(self.size, min_size_px) / 2
        return np.hstack([self.uv - half, self.uv + half])

    def as_json(self) -> list[dict]:
        return [{"uv": [round(float(u), 3), round(float(v), 3)], "score": round(float(s), 4)}
                for (u, v), s in zip(self.uv, self.score, strict=True)]
