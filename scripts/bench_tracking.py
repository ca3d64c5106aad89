"""Marker tracking against the exact marker ids (IDF1, ID switches, MOTA with motmetrics) on the held-out
sequences, and where box-overlap association breaks.

    .venv/bin/python scripts/bench_tracking.py [--model MODEL.pt]   (default: the shipped model)

1. Sequences: each held-out sequence of datasets/perception_heldout (press, slide), track_roll (roll) and
   track_large (1.5 mm press and slide: large deformation), left camera; detections by the learned detector;
   trackers: ByteTrack with IoU on boxes enlarged 3x (the default), the same with ByteTrack's own score split of
   0.5 (only detections scoring 0.5 or more start a track; by default every detection the detector reports can:
   ``Detections.confident_from``), with centre-distance association, with IoU on the detector's boxes, and the
   Farneback optical-flow baseline. Matching radius 2 px.
2. Step sweep: the markers of a real frame (exact ``uv_centroid``) translated by s px per frame for 8
   frames, s = 1..14 px: IDF1 of each association. Markers are about 7 px wide: IoU on their boxes fails
   once s nears that; the centre distance holds up to its gate, enlarged boxes a little further.
Writes the BENCHMARKS.md section ``tracking`` and docs/figures/tracking_step_sweep.png.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, update_section  # noqa: E402

from transtac_sim.perception.dataset_files import MarkerTruth, labelled_images, sequences  # noqa: E402
from transtac_sim.perception.detection import Detections  # noqa: E402
from transtac_sim.perception.detection.model_file import DEFAULT_MODEL  # noqa: E402
from transtac_sim.perception.detection.runtime import LearnedDetector  # noqa: E402
from transtac_sim.perception.evaluation.tracking import tracking_metrics  # noqa: E402
from transtac_sim.perception.images import read_color_image  # noqa: E402
from transtac_sim.perception.tracking.bytetrack import track_bytetrack  # noqa: E402
from transtac_sim.perception.tracking.flow import track_flow  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
TRACKERS = {
    "ByteTrack, IoU on 3x boxes (default)": lambda dets, ims: track_bytetrack(dets, "iou_enlarged"),
    "the same, ByteTrack's score split 0.5": lambda dets, ims: track_bytetrack(dets, "iou_enlarged", score_split=0.5),
    "ByteTrack, centre distance": lambda dets, ims: track_bytetrack(dets, "centre"),
    "ByteTrack, IoU": lambda dets, ims: track_bytetrack(dets, "iou"),
    "Farneback flow": lambda dets, ims: track_flow(dets, ims),
}
CONDITION = {"perception_heldout": "press + slide", "track_roll": "roll", "track_large": "large (1.5 mm press, slide)"}


def main(model: Path = typer.Option(DEFAULT_MODEL), datasets_root: Path = typer.Option(REPO / "datasets"),
         write: bool = typer.Option(True), figure: Path = typer.Option(REPO / "docs/figures/tracking_step_sweep.png")) -> None:
    det = LearnedDetector(model, device="cpu")
    rows, seconds = [], {k: 0.0 for k in TRACKERS}
    frames_total = 0
    sweep_base = None
    for name, cond in CONDITION.items():
        ds = datasets_root / name
        if not ds.is_dir():
            continue
        for seq in sequences(ds):
            lis = list(labelled_images(ds, only={seq}, cameras=("left",)))
            if len(lis) < 3:
                continue
            sweep_base = sweep_base if sweep_base is not None else lis[0].truth.uv
            images = [read_color_image(li.uv_path) for li in lis]
            dets = [det.detect([im])[0] for im in images]
            truth = [li.truth for li in lis]
            frames_total += len(lis)
            for tname, run in TRACKERS.items():
                t0 = time.perf_counter()
                res = run(dets, images)
                seconds[tname] += time.perf_counter() - t0
                m = tracking_metrics(truth, res)
                rows.append(f"| {cond} | {name}/{seq} ({len(lis)} frames) | {tname} | {m['idf1']:.4f} | {m['num_switches']} | "
                            f"{m['mota']:.4f} | {m['num_misses']} | {m['num_false_positives']} |")
    steps = np.arange(1, 15)
    sweep = {a: [] for a in ("centre", "iou", "iou_enlarged")}
    for s in steps:
        truth, dets = [], []
        for f in range(8):
            uv = sweep_base + [s * f, 0.0]
            ids = np.arange(len(uv))
            truth.append(MarkerTruth(ids, uv, np.zeros((len(ids), 4))))
            dets.append(Detections(uv, np.full(len(uv), 0.9), np.full((len(uv), 2), 7.0)))
        for a in sweep:
            sweep[a].append(tracking_metrics(truth, track_bytetrack(dets, a))["idf1"])
    sweep_rows = [f"| {s} | " + " | ".join(f"{sweep[a][k]:.3f}" for a in sweep) + " |" for k, s in enumerate(steps)]
    md = (f"`python scripts/bench_tracking.py` on {machine_name()}, {time.strftime('%Y-%m-%d')}: learned detector "
          f"({model.name}) on the left camera, truth = exact marker ids, matching radius 2 px.\n\n"
          "| condition | sequence | tracker | IDF1 | ID switches | MOTA | misses | false positives |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- |\n" + "\n".join(rows) +
          "\n\nTracker time over all " + f"{frames_total} frames: " +
          ", ".join(f"{k} {1000 * v / max(frames_total, 1):.1f} ms/frame" for k, v in seconds.items()) +
          "\n\nStep sweep (a real layout translated s px per frame, exact positions; IDF1):\n\n"
          "| s (px/frame) | centre distance | IoU | IoU on 3x boxes |\n| --- | --- | --- | --- |\n" + "\n".join(sweep_rows))
    print(md)
    if write:
        update_section(REPO / "BENCHMARKS.md", "tracking", md)
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6.5, 4))
        for a, label in (("centre", "centre distance (gate 12 px)"), ("iou", "IoU, 7 px boxes"), ("iou_enlarged", "IoU, 3x boxes")):
            ax.plot(steps, sweep[a], "o-", label=label)
        ax.axvline(7.0, color="grey", ls=":", label="marker size")
        ax.set_xlabel("marker motion per frame (px)")
        ax.set_ylabel("IDF1")
        ax.set_title("ByteTrack association vs. motion between frames")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        fig.savefig(figure, dpi=110)


if __name__ == "__main__":
    typer.run(main)
