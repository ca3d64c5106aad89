"""The paper's stereo matching table and the triangulation error, on a dataset's exact label positions.

    .venv/bin/python scripts/bench_matching.py [DATASET ...] [--tau 3 6] [--drop 0 0.1] [--no-write]
                                               [--write-stack FILE]

DATASET: generated dataset folders (default datasets/perception_heldout). Per frame the markers come from
``labels.json``: ``uv`` (the geometric truth, in the recorded image) of those visible in each view, the
right list shuffled; the marker ids are the ground truth. For every epipolar tolerance ``--tau`` (px) and
fraction ``--drop`` of the right view's markers removed at random (missed detections: a harder
condition; 0 is the exact labels), each matcher (transtac_sim.perception.stereo) gives: correct matches
per frame, precision (correct / returned), recall (correct / markers visible in both views that were
not removed), and time per frame (the image-based ones, where the frame has its UV images: computing
the flow or disparity included). The paper's figures (on its real, hand-labelled frames) are beside.

Triangulation: the true pairs' ``uv`` and ``uv_centroid`` (what a detector finds) triangulated linearly
and through the flat stack against ``xyz_mm``, split into frames at rest and pressed (an indenter deeper
than 0.05 mm). The flat stack comes from the simulator's sensor of the dataset's hardware model
(``--write-stack`` saves it as the JSON that ``load_flat_stack`` reads).

Writes the tables into BENCHMARKS.md (section ``matching_exact_labels``) with this command and machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, update_section  # noqa: E402

from transtac_sim.perception.stereo import (  # noqa: E402
    MATCHERS,
    MatchParams,
    load_calibration,
    triangulate_linear,
    triangulate_refracted,
)
from transtac_sim.perception.stereo.image_matchers import FIELDS, image_matcher  # noqa: E402
from transtac_sim.perception.stereo.triangulation import flat_stack_from_dict  # noqa: E402
from transtac_sim.sensor.assembly import build_sensor  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
PAPER = {"delaunay": 90.8, "hungarian": 74.9, "epipolar_nn": 74.5, "farneback": 37.9, "sgbm": 28.7}
PRESSED_MM = 0.05


def stack_of_dataset(dataset: Path, hardware: str | None) -> tuple[dict, str]:
    """The flat stack (JSON dict) of the dataset's hardware model: the manifest's, else ``hardware``."""
    manifest = dataset / "manifest.json"
    relative_to = None
    if hardware is None and manifest.is_file():
        m = json.loads(manifest.read_text())
        hardware = m["scene"]["sensor"]["hardware"]
        relative_to = Path(m["scene_file"]).parent
    hardware = hardware or "transtac"
    sensor = build_sensor(hardware, relative_to=relative_to)
    stack = sensor.flat_stack_json()
    calib = json.loads((dataset / "calibration.json").read_text())
    same = all(np.allclose(calib[k], v) for k, v in sensor.calibration_json().items() if k not in ("model", "units"))
    return stack, hardware + ("" if same else " (its calibration differs from the dataset's!)")


def frames(dataset: Path) -> list[dict]:
    """Every frame's labels.json, with the frame folder under ``"_dir"``."""
    return [{**json.loads(p.read_text()), "_dir": p.parent} for p in sorted(dataset.glob("sequences/*/*/labels.json"))]


def matchers(frame_dir: Path) -> dict:
    """The point matchers and, where the frame has its UV images, the image-based ones."""
    images = [cv2.imread(str(frame_dir / f"{cam}_uv.png")) for cam in ("left", "right")]
    if any(im is None for im in images):
        return dict(MATCHERS)
    return {**MATCHERS, **{name: image_matcher(name, *images) for name in FIELDS}}


def view(markers: list[dict], camera: str, key: str = "uv") -> tuple[np.ndarray, np.ndarray]:
    vis = [m for m in markers if m[camera]["visible"] and m[camera][key] is not None]
    return np.array([m["id"] for m in vis], dtype=np.int64), np.array([m[camera][key] for m in vis]).reshape(-1, 2)


def bench_matching(dataset: Path, taus: list[float], drops: list[float]) -> list[dict]:
    calib, labels = load_calibration(dataset), frames(dataset)
    rows = []
    for tau in taus:
        for drop in drops:
            rng = np.random.default_rng(0)
            acc: dict[str, np.ndarray] = {}  # per method: correct, returned, truth, seconds
            for lab in labels:
                lid, lu = view(lab["markers"], "left")
                rid, ru = view(lab["markers"], "right")
                keep = rng.permutation(np.flatnonzero(rng.random(len(rid)) >= drop))
                rid, ru = rid[keep], ru[keep]
                truth = len(np.intersect1d(lid, rid))
                for name, matcher in matchers(lab["_dir"]).items():
                    t0 = time.perf_counter()
                    pairs = matcher(lu, ru, calib, MatchParams(tau_epi_px=tau))
                    dt = time.perf_counter() - t0
                    acc[name] = acc.get(name, np.zeros(4)) + [np.sum(lid[pairs[:, 0]] == rid[pairs[:, 1]]), len(pairs), truth, dt]
            for name, (ok, found, truth, sec) in acc.items():
                n = len(labels)
                rows.append({"tau": tau, "drop": drop, "method": name, "frames": n, "both": truth / n,
                             "correct": ok / n, "precision": ok / max(found, 1), "recall": ok / max(truth, 1),
                             "ms": 1000 * sec / n})
    return rows


def bench_triangulation(dataset: Path, stack: dict) -> list[dict]:
    calib, fs = load_calibration(dataset), flat_stack_from_dict(stack)
    errors: dict[tuple[str, str, str], list[np.ndarray]] = {}
    for lab in frames(dataset):
        state = "pressed" if any(i["depth_mm"] > PRESSED_MM for i in lab["indenters"]) else "rest"
        xyz = {m["id"]: m["xyz_mm"] for m in lab["markers"]}
        for key in ("uv", "uv_centroid"):
            lid, lu = view(lab["markers"], "left", key)
            rid, ru = view(lab["markers"], "right", key)
            ids, il, ir = np.intersect1d(lid, rid, return_indices=True)
            X = np.array([xyz[i] for i in ids]).reshape(-1, 3)
            for name, tri in (("linear", lambda a, b: triangulate_linear(calib, a, b)),
                              ("refraction-aware", lambda a, b: triangulate_refracted(calib, fs, a, b))):
                err = np.linalg.norm(tri(lu[il], ru[ir]) - X, axis=1)
                errors.setdefault((key, name, state), []).append(err)
    rows = []
    for (key, name, state), e in sorted(errors.items()):
        e = np.concatenate(e)
        rows.append({"positions": key, "method": name, "frames": state, "markers": len(e),
                     "median": float(np.median(e)), "p95": float(np.percentile(e, 95)), "max": float(e.max())})
    return rows


def markdown(command: str, results: list[tuple[Path, str, list[dict], list[dict]]]) -> str:
    load = os.getloadavg()[0]
    out = [f"`{command}` on {machine_name()} (shared: load average {load:.1f} at the end, so the times are "
           f"upper bounds), {time.strftime('%Y-%m-%d')}. Exact label positions (`uv`), the "
           "right list shuffled; `drop` = fraction of right-view markers removed at random (missed detections). "
           "Paper: average correct matches per frame on its real frames (not the same markers or counts)."]
    for dataset, hardware, match_rows, tri_rows in results:
        n = match_rows[0]["frames"]
        out += ["", f"### {dataset.name} ({n} frames, hardware `{hardware}`)", "",
                "| tau_epi px | drop | method | visible both /frame | correct /frame | precision | recall | ms /frame "
                "| paper correct /frame |", "|---|---|---|---|---|---|---|---|---|"]
        out += [f"| {r['tau']:g} | {r['drop']:g} | {r['method']} | {r['both']:.1f} | {r['correct']:.1f} | "
                f"{r['precision']:.4f} | {r['recall']:.4f} | {r['ms']:.2f} | {PAPER[r['method']]} |" for r in match_rows]
        out += ["", "| positions | triangulation | frames | markers | median mm | p95 mm | max mm |",
                "|---|---|---|---|---|---|---|"]
        out += [f"| `{r['positions']}` | {r['method']} | {r['frames']} | {r['markers']} | {r['median']:.3g} | "
                f"{r['p95']:.3g} | {r['max']:.3g} |" for r in tri_rows]
    return "\n".join(out)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("datasets", nargs="*", type=Path, default=[REPO / "datasets" / "perception_heldout"])
    p.add_argument("--tau", nargs="+", type=float, default=[3.0, 6.0], help="epipolar tolerances (px)")
    p.add_argument("--drop", nargs="+", type=float, default=[0.0, 0.1], help="fractions of right markers removed")
    p.add_argument("--hardware", help="hardware model when a dataset has no manifest.json (default transtac)")
    p.add_argument("--write-stack", type=Path, help="write the first dataset's flat stack JSON here")
    p.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    a = p.parse_args()
    results = []
    for ds in a.datasets:
        stack, hardware = stack_of_dataset(ds, a.hardware)
        if a.write_stack and not results:
            a.write_stack.write_text(json.dumps(stack, indent=1) + "\n")
        results.append((ds, hardware, bench_matching(ds, a.tau, a.drop), bench_triangulation(ds, stack)))
    command = "python scripts/bench_matching.py " + shlex.join(sys.argv[1:])
    md = markdown(command.strip(), results)
    print(md)
    if not a.no_write:
        update_section(REPO / "BENCHMARKS.md", "matching_exact_labels", md)


if __name__ == "__main__":
    main()
