"""The real chain: ``reconstruct`` (learned detector, tracking, each matcher, refraction-aware triangulation)
on the held-out sequences, scored against the exact labels: correct matches per frame, precision, recall of
the markers visible in both views, 3D error of the correct matches, and the time per stage.

    .venv/bin/python scripts/bench_reconstruct.py [DATASET ...]   (default: the held-out sets in datasets/)

A match is correct when its left and right detections are within 2 px of the same marker's ``uv_centroid``
in each view. Writes the BENCHMARKS.md section ``reconstruct_learned_detector``.
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_matching import stack_of_dataset  # noqa: E402
from benchmarks_md import machine_name, update_section  # noqa: E402

from transtac_sim.perception.dataset_files import labelled_images, sequences  # noqa: E402
from transtac_sim.perception.reconstruct import reconstruct  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MATCHERS = ["delaunay", "hungarian", "epipolar_nn", "farneback", "sgbm"]
PAPER = {"delaunay": 90.8, "hungarian": 74.9, "epipolar_nn": 74.5, "farneback": 37.9, "sgbm": 28.7}


def _nearest_id(uv: np.ndarray, truth_uv: np.ndarray, ids: np.ndarray) -> np.ndarray:
    if len(uv) == 0 or len(truth_uv) == 0:
        return np.full(len(uv), -1)
    d = np.linalg.norm(uv[:, None] - truth_uv[None], axis=2)
    k = d.argmin(1)
    return np.where(d[np.arange(len(uv)), k] <= 2.0, ids[k], -1)


def score(out: Path, dataset: Path, seq: str) -> dict:
    lis = {(li.frame, li.camera): li for li in labelled_images(dataset, only={seq})}
    frames = sorted({f for f, _ in lis})
    correct = wrong = both = 0
    errors, seconds = [], {}
    for k, f in enumerate(frames):
        rec = json.loads((out / "frames" / f"{k:06d}.json").read_text())
        L, R = lis[(f, "left")], lis[(f, "right")]
        xyz = {m["id"]: np.array(m["xyz_mm"]) for m in L.labels["markers"]}
        both += len(set(L.truth.ids) & set(R.truth.ids))
        il = _nearest_id(np.array(rec["left"]).reshape(-1, 2), L.truth.uv, L.truth.ids)
        ir = _nearest_id(np.array(rec["right"]).reshape(-1, 2), R.truth.uv, R.truth.ids)
        for m in rec["matches"]:
            a, b = il[m["left"]], ir[m["right"]]
            if a >= 0 and a == b:
                correct += 1
                errors.append(np.linalg.norm(np.array(m["xyz_mm"]) - xyz[a]))
            else:
                wrong += 1
        for key, v in rec["seconds"].items():
            seconds[key] = seconds.get(key, 0.0) + v
    n = len(frames)
    return {"frames": n, "correct": correct, "wrong": wrong, "both": both, "errors": errors,
            "seconds": {k: v / n for k, v in seconds.items()}}


def main(datasets: list[Path] = typer.Argument(None, help="dataset folders (default: datasets/perception_heldout, "
                                                        "track_roll and track_large, those that exist)")) -> None:
    datasets = datasets or [REPO / "datasets" / n for n in ("perception_heldout", "track_roll", "track_large")
                            if (REPO / "datasets" / n).is_dir()]
    rows = []
    for ds in datasets:
        stack, _ = stack_of_dataset(ds, None)
        with tempfile.TemporaryDirectory() as tmp:
            (Path(tmp) / "stack.json").write_text(json.dumps(stack))
            for m in MATCHERS:
                agg = {"frames": 0, "correct": 0, "wrong": 0, "both": 0, "errors": [], "seconds": {}}
                for seq in sequences(ds):
                    out = Path(tmp) / f"{m}_{seq}"
                    reconstruct(out, dataset=ds, sequence=seq, matcher=m, stack=Path(tmp) / "stack.json", device="cpu")
                    s = score(out, ds, seq)
                    for k in ("frames", "correct", "wrong", "both"):
                        agg[k] += s[k]
                    agg["errors"] += s["errors"]
                    for k, v in s["seconds"].items():
                        agg["seconds"][k] = agg["seconds"].get(k, 0.0) + v * s["frames"]
                n = agg["frames"]
                e = np.array(agg["errors"])
                p = agg["correct"] / max(agg["correct"] + agg["wrong"], 1)
                r = agg["correct"] / max(agg["both"], 1)
                sec = ", ".join(f"{k} {1000 * v / n:.1f}" for k, v in agg["seconds"].items())
                rows.append(f"| {ds.name} | {m} | {n} | {agg['both'] / n:.1f} | {agg['correct'] / n:.1f} | {p:.4f} | {r:.4f} | "
                            f"{np.median(e):.4f} | {np.percentile(e, 95):.4f} | {PAPER[m]} | {sec} |")
                print(rows[-1], flush=True)
    md = (f"`python scripts/bench_reconstruct.py` on {machine_name()}, {time.strftime('%Y-%m-%d')}: `reconstruct` with the shipped "
          "learned detector, ByteTrack, each matcher and refraction-aware triangulation (the dataset's flat stack), against "
          "the exact labels. Paper: correct matches per frame on its real frames.\n\n"
          "| dataset | matcher | frames | visible both /frame | correct /frame | precision | recall | 3D median mm | 3D p95 mm | "
          "paper correct /frame | ms per frame |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n" + "\n".join(rows))
    update_section(REPO / "BENCHMARKS.md", "reconstruct_learned_detector", md)


if __name__ == "__main__":
    typer.run(main)
