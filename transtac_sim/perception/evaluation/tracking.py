"""Tracking against the exact marker ids with ``motmetrics``: per frame the visible markers (id, centre)
are the ground truth, the tracker's (track id, centre) the hypotheses, matched within ``max_distance_px``.
Reports IDF1, ID switches, MOTA, and the counts behind them."""

from __future__ import annotations

from transtac_sim.perception.dataset_files import MarkerTruth
from transtac_sim.perception.tracking import TrackResult


def tracking_metrics(truth: list[MarkerTruth], result: TrackResult, max_distance_px: float = 2.0) -> dict:
    import motmetrics as mm

    acc = mm.MOTAccumulator(auto_id=True)
    for t, uv, ids in zip(truth, result.uv, result.track_ids, strict=True):
        keep = ids >= 0
        d = mm.distances.norm2squared_matrix(t.uv, uv[keep], max_d2=max_distance_px**2)
        acc.update(t.ids.tolist(), ids[keep].tolist(), d)
    names = ["idf1", "num_switches", "mota", "num_frames", "num_objects", "num_misses", "num_false_positives"]
    summary = mm.metrics.create().compute(acc, metrics=names, name="seq")
    return {k: (float(summary[k].iloc[0]) if k in ("idf1", "mota") else int(summary[k].iloc[0])) for k in names}
