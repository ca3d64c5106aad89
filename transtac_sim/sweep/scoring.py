"""The perception pipeline on a rendered benchmark set, scored against its exact labels.

Per sequence of the set (``sequences/<seq>/<frame>/{left,right}_uv.png`` + ``labels.json``): detect in both
views, track the left view's markers over the sequence (ByteTrack), match left to right, triangulate through
the flat stack of the point's sensor (refraction-aware). Scores, as the benchmark scripts compute them
(scripts/bench_detection.py, bench_tracking.py, bench_reconstruct.py), with the library's evaluation modules:

- detection precision and recall at 2 px against the visible markers' ``uv_centroid`` (both views;
  ``perception.evaluation.detection.DetectionTally``);
- stereo matches: a match is correct when its left and right detections are within 2 px of the same
  marker's ``uv_centroid`` in each view; correct matches per frame, precision (correct / returned) and
  recall (correct / markers visible in both views);
- tracking IDF1 of the left view against the marker ids (``perception.evaluation.tracking``), the mean over
  the sequences;
- reconstruction error: distance (mm) of each correct match's triangulated point from the marker's
  ``xyz_mm``, median and 95th percentile;
- seconds per frame of each stage (detect counts both views).
"""

from __future__ import annotations

import json
import time
from functools import lru_cache
from pathlib import Path

import numpy as np

from transtac_sim.perception.dataset_files import labelled_images, sequences
from transtac_sim.perception.evaluation.detection import DetectionTally
from transtac_sim.perception.evaluation.tracking import tracking_metrics
from transtac_sim.perception.images import read_color_image
from transtac_sim.perception.tracking.bytetrack import track_bytetrack

RADIUS_PX = 2.0
MIN_MARKERS = 3


@lru_cache(maxsize=4)
def _detector(method: str, width: int, height: int):
    """The detector, once per process and image size; the learned one refuses a size it was not trained on
    (PerceptionInputError naming it)."""
    from transtac_sim.perception.detect import make_detector

    return make_detector(method, None, "cpu", images=[(f"a {width}x{height} benchmark image", np.zeros((height, width, 3), np.uint8))])[0]


def nearest_id(uv: np.ndarray, truth_uv: np.ndarray, ids: np.ndarray, radius_px: float = RADIUS_PX) -> np.ndarray:
    """Per detection, the id of the nearest true marker within ``radius_px``, else -1."""
    if len(uv) == 0 or len(truth_uv) == 0:
        return np.full(len(uv), -1)
    d = np.linalg.norm(uv[:, None] - truth_uv[None], axis=2)
    k = d.argmin(1)
    return np.where(d[np.arange(len(uv)), k] <= radius_px, ids[k], -1)


def score_dataset(dataset: Path, stack: dict, *, detector: str = "learned", matcher: str = "delaunay") -> dict:
    """Run the pipeline on every sequence of ``dataset`` and score it (module docstring)."""
    from transtac_sim.perception.stereo import MATCHERS, MatchParams, load_calibration, triangulate_refracted
    from transtac_sim.perception.stereo.triangulation import flat_stack_from_dict

    dataset = Path(dataset)
    calib, flat = load_calibration(dataset / "calibration.json"), flat_stack_from_dict(stack)
    match = MATCHERS[matcher]
    tally = DetectionTally(radii_px=(RADIUS_PX,))
    correct = wrong = both = frames = 0
    errors, idf1 = [], []
    sec = {"detect": 0.0, "track": 0.0, "match": 0.0, "triangulate": 0.0}
    for seq in sequences(dataset):
        lis = {(li.frame, li.camera): li for li in labelled_images(dataset, only={seq})}
        order = sorted({f for f, _ in lis if (f, "left") in lis and (f, "right") in lis})
        if not order:
            continue
        dets = []
        for f in order:
            L, R = lis[(f, "left")], lis[(f, "right")]
            ims = [read_color_image(L.uv_path), read_color_image(R.uv_path)]
            detect = _detector(detector, ims[0].shape[1], ims[0].shape[0])
            t0 = time.perf_counter()
            dl, dr = detect(ims)
            sec["detect"] += time.perf_counter() - t0
            tally.add(dl.uv, L.truth.uv)
            tally.add(dr.uv, R.truth.uv)
            dets.append((dl, dr))
        t0 = time.perf_counter()
        tracks = track_bytetrack([d[0] for d in dets])
        sec["track"] += time.perf_counter() - t0
        idf1.append(tracking_metrics([lis[(f, "left")].truth for f in order], tracks, RADIUS_PX)["idf1"])
        for f, (dl, dr) in zip(order, dets, strict=True):
            L, R = lis[(f, "left")], lis[(f, "right")]
            frames += 1
            both += len(set(L.truth.ids.tolist()) & set(R.truth.ids.tolist()))
            t0 = time.perf_counter()
            pairs = (np.asarray(match(dl.uv, dr.uv, calib, MatchParams()), dtype=int).reshape(-1, 2)
                     if len(dl) >= MIN_MARKERS and len(dr) >= MIN_MARKERS else np.zeros((0, 2), int))
            t1 = time.perf_counter()
            xyz = triangulate_refracted(calib, flat, dl.uv[pairs[:, 0]], dr.uv[pairs[:, 1]])
            sec["match"] += t1 - t0
            sec["triangulate"] += time.perf_counter() - t1
            il = nearest_id(dl.uv, L.truth.uv, L.truth.ids)
            ir = nearest_id(dr.uv, R.truth.uv, R.truth.ids)
            truth_xyz = {m["id"]: m["xyz_mm"] for m in L.labels["markers"]}
            for (i, j), p in zip(pairs, xyz, strict=True):
                a = il[i]
                if a >= 0 and a == ir[j]:
                    correct += 1
                    errors.append(float(np.linalg.norm(p - np.asarray(truth_xyz[int(a)]))))
                else:
                    wrong += 1
    if frames == 0:
        raise RuntimeError(f"{dataset}: no complete stereo frame to score")
    s = tally.summary()
    e = np.asarray(errors)
    return {
        "frames": frames,
        "detection_precision": s[f"precision@{RADIUS_PX:g}px"], "detection_recall": s[f"recall@{RADIUS_PX:g}px"],
        "visible_both_per_frame": both / frames, "correct_matches_per_frame": correct / frames,
        "match_precision": correct / max(correct + wrong, 1), "match_recall": correct / max(both, 1),
        "tracking_idf1": float(np.mean(idf1)),
        "reconstruction_error_mm": float(np.median(e)) if len(e) else float("nan"),
        "reconstruction_error_p95_mm": float(np.percentile(e, 95)) if len(e) else float("nan"),
        **{f"seconds_{k}_per_frame": v / frames for k, v in sec.items()},
    }


def read_json(path: Path) -> dict:
    return json.loads(Path(path).read_text())
