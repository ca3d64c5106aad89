"""Speed of the stereo reconstruction chain, stage by stage, on the held-out sequences.

    .venv/bin/python scripts/bench_chain_speed.py [--device cpu|cuda] [--repeats 3] [--md-out FILE] [DATASET ...]

DATASET: generated dataset folders (default: datasets/perception_heldout, track_roll and track_large where
present). Every sequence is run ``--repeats`` times after a warm-up (the first pair detected three times,
one pass of every other stage, the tracker's imports). Stages, each timed on its own (wall clock):

- detect: the shipped learned detector (``perception.detect.make_detector``) on both UV views as one batch
  (onnxruntime on the CPU, PyTorch on ``--device cuda``); one time per stereo frame.
- track: ByteTrack (``tracking.bytetrack``, IoU on 3x boxes) on the left view's detections of the whole
  sequence; one time per pass, divided by the sequence's frames.
- match: each point matcher (``stereo.MATCHERS``: delaunay, hungarian, epipolar_nn) on the detections,
  and the image-based farneback and sgbm matchers (the flow or disparity of the UV pair included).
- triangulate: the delaunay matches, linearly and refraction-aware (the dataset's flat stack).
- dense (separate from the chain), where the frames have white-light images: SGBM on the pair alone
  (``stereo.dense.dense_points``), and reconstruct's whole fusion of a frame (``perception.fuse.fuse_frame``:
  SGBM, its alignment to the triangulated markers, the depth map and point cloud written to a temporary
  folder).
The point matchers and the triangulations take about a millisecond: each is run ``--inner`` times per
frame and every run is one sample; they run for all frames of a pass before the image-based matchers and
the dense stages (whose OpenCV threads would otherwise compete with them). A stage's figure is the median over its samples (ms per stereo
frame). The chain is detect + track + delaunay + refraction-aware triangulation: the sum of those
medians, and the measured pass (the mean per frame of each sequence pass, median over passes).

Writes the BENCHMARKS.md section ``chain_speed_cpu`` or ``chain_speed_gpu`` (by ``--device``), or with
``--md-out FILE`` the section text to FILE only (bring it in with ``python scripts/benchmarks_md.py SECTION
FILE``). Needs only the repository and the datasets.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_matching import stack_of_dataset  # noqa: E402
from benchmarks_md import machine_name, update_section  # noqa: E402

from transtac_sim.perception.dataset_files import sequences  # noqa: E402
from transtac_sim.perception.detect import make_detector  # noqa: E402
from transtac_sim.perception.images import read_color_image  # noqa: E402
from transtac_sim.perception.stereo import MATCHERS, MatchParams, image_matcher, load_calibration  # noqa: E402
from transtac_sim.perception.stereo.triangulation import (  # noqa: E402
    flat_stack_from_dict,
    triangulate_linear,
    triangulate_refracted,
)
from transtac_sim.perception.tracking.bytetrack import track_bytetrack  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATASETS = ("perception_heldout", "track_roll", "track_large")
IMAGE_MATCHERS = ("farneback", "sgbm")
CHAIN = ("detect", "track", "match delaunay", "triangulate refraction-aware")


def _sequence_frames(dataset: Path, seq: str) -> list[dict]:
    """The frames of a sequence that have both UV images: uv (left, right) and, if present, white images."""
    out = []
    for fdir in sorted((dataset / "sequences" / seq).iterdir()):
        if not ((fdir / "labels.json").is_file() and (fdir / "left_uv.png").is_file() and (fdir / "right_uv.png").is_file()):
            continue
        white = [fdir / f"{cam}_white.png" for cam in ("left", "right")]
        out.append({"uv": [read_color_image(fdir / f"{cam}_uv.png") for cam in ("left", "right")],
                    "white": [read_color_image(p) for p in white] if all(p.is_file() for p in white) else None})
    return out


def _timed(fn, *args) -> tuple[object, float, float]:
    """fn(*args), its wall-clock seconds and the process's CPU seconds (all threads) meanwhile."""
    t0, c0 = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - t0, time.process_time() - c0


def _image_match(name: str, images: list[np.ndarray], left_uv: np.ndarray, right_uv: np.ndarray, calib,
                 params: MatchParams) -> np.ndarray:
    """The farneback or sgbm matcher of one frame, built and run (the flow or disparity included)."""
    return image_matcher(name, images[0], images[1])(left_uv, right_uv, calib, params)


def _dense(calib, white: list[np.ndarray], lu: np.ndarray, ru: np.ndarray, xyz: np.ndarray,
           tmp: Path) -> tuple[tuple[float, float], tuple[float, float]]:
    """(Wall, CPU) seconds of the dense SGBM points alone, and of reconstruct's whole fusion of the frame (``fuse_frame``:
    SGBM, alignment to the markers, the depth map and point cloud written to ``tmp``)."""
    from transtac_sim.perception.fuse import fuse_frame
    from transtac_sim.perception.stereo.dense import dense_points

    d_ref = float(np.median(calib.rectified(lu, "left")[:, 0] - calib.rectified(ru, "right")[:, 0]))
    _, t_sgbm, c_sgbm = _timed(dense_points, calib, white[0], white[1], d_ref)
    _, t_fuse, c_fuse = _timed(fuse_frame, calib, white[0], white[1], lu, ru, xyz, tmp / "frame")
    return (t_sgbm, c_sgbm), (t_fuse, c_fuse)


def run(datasets: list[Path], device: str, repeats: int, inner: int) -> tuple[dict[str, list[float]], dict]:
    detect, _ = make_detector("learned", None, device)
    params = MatchParams()
    samples: dict[str, list[float]] = {}  # wall seconds; CPU seconds under "cpu " + stage
    counts = {"frames": 0, "left": [], "right": [], "matches": [], "sequences": 0, "passes": []}

    def add(stage: str, seconds: float, cpu: float) -> None:
        samples.setdefault(stage, []).append(seconds)
        samples.setdefault("cpu " + stage, []).append(cpu)

    tmp = Path(tempfile.mkdtemp(prefix="bench_chain_speed_"))
    warm = True  # the first pass of the first sequence warms every stage up and is not recorded
    for ds in datasets:
        calib = load_calibration(ds)
        stack = flat_stack_from_dict(stack_of_dataset(ds, None)[0])
        for seq in sequences(ds):
            frames = _sequence_frames(ds, seq)
            if not frames:
                continue
            counts["sequences"] += 1
            counts["frames"] += len(frames)
            warmup, warm = warm, False
            for r in range(repeats + warmup):
                record, first = r >= warmup, r == warmup
                chain = 0.0
                dets = []
                for fr in frames:
                    if not record:
                        for _ in range(3):
                            detect(fr["uv"])
                    d, t, cpu = _timed(detect, fr["uv"])
                    dets.append(d)
                    chain += t
                    if record:
                        add("detect", t, cpu)
                _, t, cpu = _timed(track_bytetrack, [d[0] for d in dets])
                chain += t
                if record:
                    add("track", t / len(frames), cpu / len(frames))
                # the point stages of every frame first, then the image-based ones (OpenCV's threads), then dense
                matched = []
                for dl, dr in dets:
                    for name, matcher in MATCHERS.items():
                        for _ in range(inner if record else 1):
                            pairs, t, cpu = _timed(matcher, dl.uv, dr.uv, calib, params)
                            if record:
                                add(f"match {name}", t, cpu)
                        if name == "delaunay":
                            chain += t
                            delaunay_pairs = pairs
                    lu, ru = dl.uv[delaunay_pairs[:, 0]], dr.uv[delaunay_pairs[:, 1]]
                    for _ in range(inner if record else 1):
                        _, t, cpu = _timed(triangulate_linear, calib, lu, ru)
                        if record:
                            add("triangulate linear", t, cpu)
                        xyz, t, cpu = _timed(triangulate_refracted, calib, stack, lu, ru)
                        if record:
                            add("triangulate refraction-aware", t, cpu)
                    chain += t
                    matched.append((lu, ru, xyz))
                    if first:
                        counts["left"].append(len(dl))
                        counts["right"].append(len(dr))
                        counts["matches"].append(len(delaunay_pairs))
                for fr, (dl, dr) in zip(frames, dets, strict=True):
                    for name in IMAGE_MATCHERS:
                        _, t, cpu = _timed(_image_match, name, fr["uv"], dl.uv, dr.uv, calib, params)
                        if record:
                            add(f"match {name}", t, cpu)
                for fr, (lu, ru, xyz) in zip(frames, matched, strict=True):
                    if fr["white"] is not None and len(xyz) >= 3 and "dense_error" not in counts:
                        try:
                            sgbm, fuse = _dense(calib, fr["white"], lu, ru, xyz, tmp)
                        except (ImportError, TypeError) as e:  # stereo.dense / perception.fuse changed
                            counts["dense_error"] = f"{type(e).__name__}: {e}"
                        else:
                            if record:
                                add("dense SGBM", *sgbm)
                                add("dense fusion", *fuse)
                if record:
                    counts["passes"].append(chain / len(frames))
    shutil.rmtree(tmp, ignore_errors=True)
    return samples, counts


def markdown(command: str, device: str, samples: dict[str, list[float]], counts: dict, repeats: int, inner: int,
             load: tuple[float, float]) -> str:
    med = {k: 1000 * float(np.median(v)) for k, v in samples.items()}
    p90 = {k: 1000 * float(np.percentile(v, 90)) for k, v in samples.items()}
    where = machine_name(device)
    detector = "onnxruntime" if device == "cpu" else "PyTorch float32"
    loads = f", load average {load[0]:.1f} at the start and {load[1]:.1f} at the end (shared machine: upper bounds)" \
        if device == "cpu" else ""
    notes = {"detect": f"learned ({detector}), both views in one batch", "track": "ByteTrack, IoU on 3x boxes, left view; "
             "per pass / frames", "match delaunay": "prior-guided Delaunay", "match farneback": "flow of the UV pair included",
             "match sgbm": "SGBM of the UV pair included", "dense SGBM": "white-light pair: rectified, SGBM, 3D points",
             "dense fusion": "reconstruct's fuse_frame: SGBM, similarity to the markers, EXR + PLY written"}
    order = ["detect", "track", *(f"match {m}" for m in (*MATCHERS, *IMAGE_MATCHERS)), "triangulate linear",
             "triangulate refraction-aware", "dense SGBM", "dense fusion"]
    rows = [f"| {k.split(' ', 1)[0]} | {k.split(' ', 1)[1] if ' ' in k else k} | {med[k]:.2f} | {p90[k]:.2f} | "
            f"{med['cpu ' + k]:.2f} | {len(samples[k])} | {notes.get(k, '')} |" for k in order if k in samples]
    chain = sum(med[k] for k in CHAIN)
    passes = 1000 * float(np.median(counts["passes"]))
    mt = med["match delaunay"] + med["triangulate refraction-aware"]
    mt_cpu = med["cpu match delaunay"] + med["cpu triangulate refraction-aware"]
    return (f"`{command}` on {where}{loads}, {time.strftime('%Y-%m-%d')}: {counts['sequences']} sequences, "
            f"{counts['frames']} stereo frames of 640x480 x {repeats} passes after a warm-up; per frame "
            f"{np.mean(counts['left']):.1f} left and {np.mean(counts['right']):.1f} right detections, "
            f"{np.mean(counts['matches']):.1f} delaunay matches. Point matchers and triangulations run {inner} times "
            "per frame. Median and 90th percentile of the samples, ms per stereo frame (wall clock); CPU: the process's "
            "CPU time (all its threads: onnxruntime's and OpenCV's too), less sensitive to other jobs on a shared machine."
            "\n\n"
            "| stage | method | median ms | p90 ms | median CPU ms | samples | note |\n"
            "| --- | --- | --- | --- | --- | --- | --- |\n"
            + "\n".join(rows) +
            f"\n\nMatch (delaunay) + triangulate (refraction-aware): **{mt:.2f} ms** per stereo frame (CPU {mt_cpu:.2f} ms).\n"
            f"Chain (detect + track + delaunay + refraction-aware triangulation): **{chain:.1f} ms** per stereo frame "
            f"(sum of the medians), **{1000 / chain:.1f} frames per second**; measured per sequence pass: "
            f"{passes:.1f} ms ({1000 / passes:.1f} frames per second). Dense fusion (SGBM + alignment + files; not in "
            f"the chain): {med.get('dense fusion', float('nan')):.1f} ms per frame."
            + (f" Dense stages skipped: {counts['dense_error']}." if "dense_error" in counts else ""))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("datasets", nargs="*", type=Path)
    p.add_argument("--device", default="cpu", help="cpu or cuda (the learned detector's device)")
    p.add_argument("--repeats", type=int, default=3, help="passes over every sequence after the warm-up")
    p.add_argument("--inner", type=int, default=5, help="runs per frame of the point matchers and triangulations")
    p.add_argument("--md-out", type=Path, help="write the section text to this file instead of BENCHMARKS.md")
    a = p.parse_args()
    datasets = a.datasets or [REPO / "datasets" / n for n in DEFAULT_DATASETS if (REPO / "datasets" / n).is_dir()]
    load0 = os.getloadavg()[0]
    samples, counts = run(datasets, a.device, max(a.repeats, 1), max(a.inner, 1))
    command = "python scripts/bench_chain_speed.py " + shlex.join(sys.argv[1:])
    md = markdown(command.strip(), a.device, samples, counts, a.repeats, a.inner, (load0, os.getloadavg()[0]))
    print(md)
    if a.md_out:
        a.md_out.write_text(md + "\n")
    else:
        update_section(REPO / "BENCHMARKS.md", f"chain_speed_{'cpu' if a.device == 'cpu' else 'gpu'}", md)


if __name__ == "__main__":
    main()
