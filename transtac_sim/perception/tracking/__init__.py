"""Marker tracking over a sequence of frames: ByteTrack (the ``trackers`` package) with a centre-distance
association (``bytetrack``), and the optical-flow baseline (``flow``). Both return :class:`TrackResult`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class TrackResult:
    """Per frame: the detections' centres (N_t, 2) px and their track ids (N_t,), -1 for untracked."""

    uv: list[np.ndarray]
    track_ids: list[np.ndarray]

    def displacements(self) -> list[np.ndarray]:
        """Per frame, each detection's displacement (px) from where its track was first seen; NaN if untracked."""
        first: dict[int, np.ndarray] = {}
        out = []
        for uv, ids in zip(self.uv, self.track_ids, strict=True):
            d = np.full_like(uv, np.nan, dtype=np.float64)
            for k, (p, t) in enumerate(zip(uv, ids, strict=True)):
                if t < 0:
                    continue
                first.setdefault(int(t), p)
                d[k] = p - first[int(t)]
            out.append(d)
        return out

    def as_json(self) -> list[dict]:
        return [{"frame": f, "markers": [{"uv": [round(float(u), 3), round(float(v), 3)], "track_id": int(t),
                                          "displacement_px": None if np.isnan(d[0]) else [round(float(d[0]), 3), round(float(d[1]), 3)]}
                                         for (u, v), t, d in zip(uv, ids, disp, strict=True)]}
                for f, (uv, ids, disp) in enumerate(zip(self.uv, self.track_ids, self.displacements(), strict=True))]
