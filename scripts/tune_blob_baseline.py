"""How the blob baseline's defaults (``BlobParams``: threshold 0.3 of the bright level, circularity 0.5) were
chosen: F1 at 2 px over a grid, on every third UV image of the training sets (never the held-out ones).

    .venv/bin/python scripts/tune_blob_baseline.py
"""

from __future__ import annotations

from pathlib import Path

import typer

from transtac_sim.perception.dataset_files import labelled_images
from transtac_sim.perception.detection.blob import BlobParams, detect_blobs
from transtac_sim.perception.evaluation.detection import DetectionTally
from transtac_sim.perception.images import read_color_image

REPO = Path(__file__).resolve().parents[1]
TRAINING = ["detector_train_rest", "detector_train_contact"]

def main() -> None:
    lis = [li for name in TRAINING for li in labelled_images(REPO / "datasets" / name)][::3]
    images = [read_color_image(li.uv_path) for li in lis]
    print("| threshold fraction | min circularity | P@2px | R@2px | F1@2px |\n| --- | --- | --- | --- | --- |")
    for thr in (0.1, 0.15, 0.2, 0.3, 0.4):
        for circ in (0.3, 0.5, 0.7):
            t = DetectionTally(radii_px=(2.0,))
            for li, im in zip(lis, images, strict=True):
                t.add(detect_blobs(im, BlobParams(threshold_fraction=thr, min_circularity=circ)).uv, li.truth.uv)
            s = t.summary()
            print(f"| {thr} | {circ} | {s['precision@2px']:.4f} | {s['recall@2px']:.4f} | {s['f1@2px']:.4f} |")


if __name__ == "__main__":
    typer.run(main)
