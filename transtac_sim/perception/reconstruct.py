"""``transtac-sim reconstruct``: metric 3D marker positions from the two cameras, frame by frame: detect in
both views, track the left view's markers over the sequence, match left to right, triangulate.

Input: a generated dataset (``calibration.json`` and one sequence's ``left_uv``/``right_uv`` images), or a
calibration file with left and right image folders (paired in sorted order), single images or videos.
Triangulation is refraction-aware when a flat-stack file is given (``stereo.triangulation``), else linear
(pinhole; about 2.6 mm off through the TransTac's backing and gel, BENCHMARKS.md ``matching_exact_labels``).

With ``dense="sgbm"`` the white-light pair of each frame also gives a dense point cloud aligned to the
frame's triangulated markers (``stereo.dense``): ``OUT/dense/<frame:06d>.exr`` (depth, mm) and ``.ply``.

Output (DESIGN.md section 6; ``docs/formats.md``): ``OUT/frames/<frame:06d>.json`` per frame,
``OUT/summary.json`` and ``OUT/preview.png`` (the last frame's matches drawn on both views). Every input is
read and checked before anything is written; each file is written atomically. A frame with fewer than
three markers in a view is written with zero matches and its reason.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.perception.detect import make_detector
from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.perception.images import ImageRef, find_images, read_color_image
from transtac_sim.perception.stereo import (
    MATCHERS,
    MatchParams,
    image_matcher,
    load_calibration,
    load_flat_stack,
)
from transtac_sim.perception.stereo.calibration import check_image_size
from transtac_sim.perception.stereo.triangulation import triangulate_linear, triangulate_refracted
from transtac_sim.perception.tracking.bytetrack import track_bytetrack
from transtac_sim.writer.atomic import atomic_write, write_json

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
MIN_MARKERS = 3


@dataclass
class ReconstructReport:
    out: Path
    frames: int
    mean_matches: float
    triangulation: str
    seconds: dict[str, float]


def _frames(source: Path) -> tuple[list[str], list[np.ndarray]]:
    """Names and 8-bit BGR frames of an image, a folder of images or a video."""
    source = Path(source)
    if source.is_file() and source.suffix.lower() in VIDEO_SUFFIXES:
        cap = cv2.VideoCapture(str(source))
        if not cap.isOpened():
            raise PerceptionInputError(source, "video cannot be opened", "check the file, or export its frames as PNG")
        frames = []
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            frames.append(frame)
        cap.release()
        if not frames:
            raise PerceptionInputError(source, "video has no frames", "check the recording")
        return [f"{source}#{i}" for i in range(len(frames))], frames
    refs: list[ImageRef] = find_images(source)
    return [r.name for r in refs], [read_color_image(r.path) for r in refs]


def _inputs(dataset: Path | None, sequence: str | None, calibration: Path | None, left: Path | None,
            right: Path | None, kind: str = "uv"):
    if dataset is not None:
        seqs = sorted(p.name for p in (Path(dataset) / "sequences").iterdir() if p.is_dir()) \
            if (Path(dataset) / "sequences").is_dir() else []
        seq = sequence or (seqs[0] if seqs else None)
        if seq not in seqs:
            raise PerceptionInputError(dataset, f"no sequence {seq!r}" if seqs else "not a dataset folder (no sequences/)",
                                       "pick one with --sequence" if seqs else "pass a folder written by `transtac-sim generate`")
        calib = load_calibration(Path(dataset) / "calibration.json")
        names_l, frames_l = zip(*[(r.name, read_color_image(r.path)) for r in find_images(dataset, f"{seq}/*/left_{kind}.png")], strict=True)
        names_r, frames_r = zip(*[(r.name, read_color_image(r.path)) for r in find_images(dataset, f"{seq}/*/right_{kind}.png")], strict=True)
        names_l, frames_l, names_r, frames_r = list(names_l), list(frames_l), list(names_r), list(frames_r)
    else:
        if calibration is None or left is None or right is None:
            raise PerceptionInputError("reconstruct", "needs --dataset, or --calibration with --left and --right",
                                       "see `transtac-sim reconstruct --help`")
        calib = load_calibration(calibration)
        names_l, frames_l = _frames(left)
        names_r, frames_r = _frames(right)
    if len(frames_l) != len(frames_r):
        raise PerceptionInputError(f"{left or dataset}, {right or dataset}",
                                   f"{len(frames_l)} left frames but {len(frames_r)} right frames",
                                   "give both cameras the same frames (paired in sorted order)")
    for n, f in zip(names_l + names_r, frames_l + frames_r, strict=True):
        check_image_size(calib, (f.shape[1], f.shape[0]), n)
    return calib, names_l, frames_l, names_r, frames_r


def reconstruct(out: Path, *, dataset: Path | None = None, sequence: str | None = None,
                calibration: Path | None = None, left: Path | None = None, right: Path | None = None,
                matcher: str = "delaunay", detector: str = "learned", model: Path | None = None,
                stack: Path | None = None, device: str = "auto", dense: str = "none",
                left_white: Path | None = None, right_white: Path | None = None,
                progress: Callable[[int, int], None] | None = None) -> ReconstructReport:
    if matcher not in (*MATCHERS, "farneback", "sgbm"):
        raise ValueError(f"unknown matcher {matcher!r} ({', '.join([*MATCHERS, 'farneback', 'sgbm'])})")
    if dense not in ("none", "sgbm"):
        raise ValueError(f"unknown dense method {dense!r} (none or sgbm)")
    calib, names_l, frames_l, names_r, frames_r = _inputs(dataset, sequence, calibration, left, right)
    whites = None
    if dense != "none":
        if dataset is None and (left_white is None or right_white is None):
            raise PerceptionInputError("reconstruct", "--dense needs the white-light images",
                                       "pass --left-white and --right-white (or a dataset with white images)")
        whites = _inputs(dataset, sequence, calibration, left_white, right_white, kind="white")
        if len(whites[2]) != len(frames_l):
            raise PerceptionInputError(left_white or dataset, f"{len(whites[2])} white-light frames but {len(frames_l)} UV frames",
                                       "give the white-light images of the same frames")
    flat = load_flat_stack(stack) if stack else None
    detect, _ = make_detector(detector, model, device, images=[*zip(names_l, frames_l, strict=True),
                                                                *zip(names_r, frames_r, strict=True)])
    n = len(frames_l)
    t0 = time.perf_counter()
    dets = [detect([a, b]) for a, b in zip(frames_l, frames_r, strict=True)]
    t_detect = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    tracks = track_bytetrack([d[0] for d in dets])
    t_track = (time.perf_counter() - t0) / n
    out = Path(out)
    params = MatchParams()
    total = 0
    for f in range(n):
        dl, dr = dets[f]
        record = {"frame": f, "source": {"left": names_l[f], "right": names_r[f]},
                  "left": np.round(dl.uv, 3).tolist(), "right": np.round(dr.uv, 3).tolist(), "matches": []}
        t1 = time.perf_counter()
        if len(dl) < MIN_MARKERS or len(dr) < MIN_MARKERS:
            pairs = np.zeros((0, 2), int)
            record["reason"] = f"too few markers (left {len(dl)}, right {len(dr)}; at least {MIN_MARKERS} each)"
        elif matcher in MATCHERS:
            pairs = MATCHERS[matcher](dl.uv, dr.uv, calib, params)
        else:
            pairs = image_matcher(matcher, frames_l[f], frames_r[f])(dl.uv, dr.uv, calib, params)
        t2 = time.perf_counter()
        pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
        lu, ru = dl.uv[pairs[:, 0]], dr.uv[pairs[:, 1]]
        xyz = triangulate_refracted(calib, flat, lu, ru) if flat is not None else triangulate_linear(calib, lu, ru)
        t3 = time.perf_counter()
        record["matches"] = [{"left": int(i), "right": int(j), "track_id": int(tracks.track_ids[f][i]),
                              "xyz_mm": np.round(p, 4).tolist()} for (i, j), p in zip(pairs, xyz, strict=True)]
        if whites is not None:
            record["dense"] = _fuse(calib, whites[2][f], whites[4][f], lu, ru, xyz, out / "dense" / f"{f:06d}")
        record["seconds"] = {"detect": t_detect, "track": t_track, "match": t2 - t1, "triangulate": t3 - t2,
                             "dense": time.perf_counter() - t3 if whites is not None else 0.0}
        write_json(out / "frames" / f"{f:06d}.json", record)
        total += len(pairs)
        if progress:
            progress(f + 1, n)
    _preview(frames_l[-1], frames_r[-1], dets[-1][0].uv, dets[-1][1].uv, pairs, out / "preview.png")
    report = ReconstructReport(out, n, total / n, "refraction-aware" if flat is not None else "linear",
                               {"detect": t_detect, "track": t_track})
    write_json(out / "summary.json", {"frames": n, "mean_matches": report.mean_matches, "matcher": matcher,
                                      "detector": detector, "triangulation": report.triangulation,
                                      "seconds_per_frame": report.seconds})
    return report


def _fuse(calib, left_white: np.ndarray, right_white: np.ndarray, left_uv: np.ndarray, right_uv: np.ndarray,
          xyz: np.ndarray, stem: Path) -> dict:
    """Dense SGBM points of the white pair aligned to the markers; writes ``stem``.exr and .ply."""
    from transtac_sim.perception.stereo.dense import (
        align_to_markers,
        dense_points,
        write_depth_exr,
        write_ply,
    )

    if len(xyz) < 3:
        return {"aligned": False, "reason": "fewer than 3 triangulated markers"}
    d_ref = float(np.median(calib.rectified(left_uv, "left")[:, 0] - calib.rectified(right_uv, "right")[:, 0]))
    points = dense_points(calib, left_white, right_white, d_ref)
    a = align_to_markers(points, calib, left_uv, xyz)
    if a is None:
        return {"aligned": False, "reason": "no similarity found (fewer than 3 consistent marker anchors)"}
    fused = a.apply(points.xyz_mm.reshape(-1, 3)).reshape(points.xyz_mm.shape)
    write_depth_exr(stem.with_suffix(".exr"), np.where(points.valid, fused[:, :, 2], np.inf))
    write_ply(stem.with_suffix(".ply"), fused[points.valid])
    return {"aligned": True, "scale": a.scale, "anchors": a.pairs, "inliers": a.inliers, "rms_mm": a.rms_mm,
            "valid_fraction": float(points.valid.mean())}


def _preview(left: np.ndarray, right: np.ndarray, uv_l: np.ndarray, uv_r: np.ndarray, pairs: np.ndarray,
             path: Path) -> Path:
    """Both views side by side (brightened), detections circled, matches joined by lines."""
    both = np.hstack([left, right]).astype(np.float32)
    both = np.clip(both * (230.0 / max(float(np.percentile(both, 99.9)), 1.0)), 0, 255).astype(np.uint8)
    w = left.shape[1]
    for u, v in uv_l:
        cv2.circle(both, (int(round(u)), int(round(v))), 5, (0, 0, 255), 1, cv2.LINE_AA)
    for u, v in uv_r:
        cv2.circle(both, (int(round(u)) + w, int(round(v))), 5, (0, 0, 255), 1, cv2.LINE_AA)
    for i, j in pairs:
        a = (int(round(uv_l[i][0])), int(round(uv_l[i][1])))
        b = (int(round(uv_r[j][0])) + w, int(round(uv_r[j][1])))
        cv2.line(both, a, b, (255, 200, 0), 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", both)
    return atomic_write(path, lambda f: f.write(buf.tobytes()))
