"""How the learned detector's default score threshold (``runtime.DEFAULT_SCORE_THRESHOLD``) was chosen:
precision, recall and F1 at 2 px on the training sets' validation split (every 8th sequence, as in
training), for a grid of thresholds. The held-out sets are not used.

    .venv/bin/python scripts/choose_score_threshold.py [--model PATH]
"""

from __future__ import annotations

from pathlib import Path

import typer

from transtac_sim.perception.detection.model_file import DEFAULT_MODEL
from transtac_sim.perception.detection.runtime import LearnedDetector
from transtac_sim.perception.evaluation.detection import DetectionTally
from transtac_sim.perception.training.train import load_samples

REPO = Path(__file__).resolve().parents[1]


def main(model: Path = typer.Option(DEFAULT_MODEL)) -> None:
    _, val = load_samples([REPO / "datasets/detector_train_rest", REPO / "datasets/detector_train_contact"])
    det = LearnedDetector(model, device="cpu", score_threshold=0.05)
    outs = [(det.detect([s.image])[0], s.uv) for s in val]
    print(f"{len(val)} validation images\n\n| threshold | P@2px | R@2px | F1@2px |\n| --- | --- | --- | --- |")
    for thr in (0.2, 0.3, 0.4, 0.5, 0.6, 0.7):
        t = DetectionTally(radii_px=(2.0,))
        for d, uv in outs:
            t.add(d.uv[d.score >= thr], uv)
        s = t.summary()
        print(f"| {thr} | {s['precision@2px']:.4f} | {s['recall@2px']:.4f} | {s['f1@2px']:.4f} |")


if __name__ == "__main__":
    typer.run(main)
