"""``transtac-sim reconstruct``: metric 3D marker positions from the two cameras, frame by frame: detect in
both views, track the left view's markers over the sequence, match left to right, triangulate.

Input: a generated dataset (``calibration.json`` and one sequence's ``left_uv``/``right_uv`` images), or a
calibration file with left and right image folders (paired in sorted order), single images or videos.
Triangulation is refraction-aware when a flat-stack file is given (``stereo.triangulation``), else linear
(pinhole; about 2.6 mm off through the TransTac's backing and gel, BENCHMARKS.md ``matching_exact_labels``).

With ``dense="sgbm"`` (or ``"onnx"`` with a local ``stereo_model`` file) the white-light pair of each frame
also gives a dense point cloud aligned to the frame's anchors (``perception.fuse``; ``anchors``: the
triangulated markers, or ``"distance-aware"``: markers plus object features, which needs ``stack``):
``OUT/dense/<frame:06d>.exr`` (depth, mm) and ``.ply``.

Output (DESIGN.md section 6; ``docs/formats.md``): ``OUT/frames/<frame:06d>.json`` per frame,
``OUT/summary.json`` and ``OUT/preview.png`` (the last frame's matches drawn on both views beside its
surface coloured by depth) or, with ``preview="video"``, ``OUT/preview.mp4`` of every frame. Every input
is read and checked before anything is written; each file is written atomically. ``OUT`` is new, empty or holds
only what reconstruct writes (an earlier run), whose files are replaced when this run ends (an interrupted run
leaves them as they were). A frame with fewer than three markers in a view is written with zero matches and its reason.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.perception.detect import make_detector
from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.perception.fuse import ANCHOR_MODES, fuse_frame
from transtac_sim.perception.images import ImageRef, find_images, read_color_image, sequence_files
from transtac_sim.perception.preview import reconstruction_panel, write_png, write_video
from transtac_sim.perception.stereo import (
    MATCHERS,
    MatchParams,
    image_matcher,
    load_calibration,
    load_flat_stack,
)
from transtac_sim.perception.stereo.calibration import check_image_size
from transtac_sim.perception.stereo.dense import OnnxStereo
from transtac_sim.perception.stereo.triangulation import triangulate_linear, triangulate_refracted
from transtac_sim.perception.tracking.bytetrack import track_bytetrack
from transtac_sim.writer.atomic import write_json
from transtac_sim.writer.staging import own_entries, staged_output

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
MIN_MARKERS = 3


@dataclass
class ReconstructReport:
    out: Path
    frames: int
    mean_matches: float
    triangulation: str
    seconds: dict[str, float]


#: what reconstruct writes into its --out folder (module docstring)
OWN_ENTRIES = ("frames", "dense", "preview.png", "preview.mp4", "summary.json")


def check_output_folder(out: Path) -> None:
    """Raise PerceptionInputError unless ``out`` is new, empty or holds only what reconstruct writes (an earlier
    run, finished or not: a summary.json there is reconstruct's), whose files this run replaces when it ends
    (writer/staging.py)."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise PerceptionInputError(out, "exists and is not a folder", "choose another --out")
    if not out.is_dir():
        return
    ours = all(p.name in OWN_ENTRIES for p in own_entries(out))
    if ours and (out / "summary.json").exists():
        try:
            summary = json.loads((out / "summary.json").read_text())
        except (OSError, ValueError):
            summary = None
        ours = isinstance(summary, dict) and {"matcher", "mean_matches"} <= summary.keys()
    if not ours:
        raise PerceptionInputError(out, "holds files that are not an earlier reconstruct output",
                                   "choose a new or empty --out (nothing was changed)")


def _earlier_files(out: Path) -> list[Path]:
    """An earlier run's files in ``out``: its frame records, dense depth, preview and summary."""
    patterns = ("frames/[0-9]*.json", "dense/[0-9]*.exr", "dense/[0-9]*.ply", "preview.png", "preview.mp4",
                "summary.json")
    return [p for pattern in patterns for p in out.glob(pattern) if p.is_file()]


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
        if calibration is not None or left is not None or right is not None:
            raise PerceptionInputError("reconstruct", "--dataset brings its own calibration.json and images",
                                       "pass --dataset alone, or --calibration with --left and --right")
        pairs = sequence_files(dataset, sequence, (f"left_{kind}.png", f"right_{kind}.png"))
        calib = load_calibration(Path(dataset) / "calibration.json")
        names_l, names_r = [a.name for a, _ in pairs], [b.name for _, b in pairs]
        frames_l, frames_r = [read_color_image(a.path) for a, _ in pairs], [read_color_image(b.path) for _, b in pairs]
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
                stereo_model: Path | None = None, anchors: str = "markers",
                left_white: Path | None = None, right_white: Path | None = None, preview: str = "png",
                progress: Callable[[int, int], None] | None = None) -> ReconstructReport:
    if matcher not in (*MATCHERS, "farneback", "sgbm"):
        raise ValueError(f"unknown matcher {matcher!r} ({', '.join([*MATCHERS, 'farneback', 'sgbm'])})")
    if dense not in ("none", "sgbm", "onnx"):
        raise ValueError(f"unknown dense method {dense!r} (none, sgbm or onnx)")
    if anchors not in ANCHOR_MODES:
        raise ValueError(f"unknown anchors {anchors!r} ({' or '.join(ANCHOR_MODES)})")
    if preview not in ("png", "video", "none"):
        raise ValueError(f"unknown preview {preview!r} (png, video or none)")
    check_output_folder(out)
    stereo = None
    if dense == "onnx":
        if stereo_model is None:
            raise PerceptionInputError("reconstruct", "--dense onnx needs the model file",
                                       "pass --stereo-model MODEL.onnx (your local export), or use --dense sgbm")
        stereo = OnnxStereo(stereo_model)
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
    if dense != "none" and anchors == "distance-aware" and (flat is None or flat.gel_thickness_mm is None):
        raise PerceptionInputError(stack or "reconstruct", "distance-aware anchors need a flat stack with gel_thickness_mm",
                                   "pass --stack with the stack's JSON (docs/formats.md), or use --anchors markers")
    detect, _ = make_detector(detector, model, device, images=[*zip(names_l, frames_l, strict=True),
                                                                *zip(names_r, frames_r, strict=True)])
    n = len(frames_l)
    t0 = time.perf_counter()
    dets = [detect([a, b]) for a, b in zip(frames_l, frames_r, strict=True)]
    t_detect = (time.perf_counter() - t0) / n
    import supervision  # noqa: F401  the tracker's imports (about a second), outside its timing
    import trackers  # noqa: F401

    t0 = time.perf_counter()
    tracks = track_bytetrack([d[0] for d in dets])
    t_track = (time.perf_counter() - t0) / n
    out = Path(out)
    with staged_output(out, _earlier_files, last=("summary.json",)) as work:
        params = MatchParams()
        total = 0
        panels: list[np.ndarray] = []
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
            dense_z = None
            if whites is not None:
                record["dense"], dense_z = fuse_frame(calib, whites[2][f], whites[4][f], lu, ru, xyz,
                                                      work / "dense" / f"{f:06d}", stack=flat, model=stereo,
                                                      anchors=anchors)
            record["seconds"] = {"detect": t_detect, "track": t_track, "match": t2 - t1, "triangulate": t3 - t2,
                                 "dense": time.perf_counter() - t3 if whites is not None else 0.0}
            write_json(work / "frames" / f"{f:06d}.json", record)
            total += len(pairs)
            if preview == "video" or (preview == "png" and f == n - 1):
                panels.append(reconstruction_panel(frames_l[f], frames_r[f], dl.uv, dr.uv, pairs, xyz, dense_z))
            if progress:
                progress(f + 1, n)
        if preview == "png":
            write_png(work / "preview.png", panels[-1])
        elif preview == "video":
            write_video(work / "preview.mp4", panels)
        report = ReconstructReport(out, n, total / n, "refraction-aware" if flat is not None else "linear",
                                   {"detect": t_detect, "track": t_track})
        write_json(work / "summary.json", {"frames": n, "mean_matches": report.mean_matches, "matcher": matcher,
                                          "detector": detector, "triangulation": report.triangulation,
                                          "seconds_per_frame": report.seconds})
    return report
