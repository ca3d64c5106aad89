"""Reconstruction error of triangulated markers against ``xyz_mm``, linear and refraction-aware, against the
indentation depth and the position in the field of view, on the exact correspondences of generated
datasets (triangulation alone: no detection or matching errors).

    .venv/bin/python scripts/bench_triangulation_error.py [DATASET ...]
        (default: datasets/perception_heldout, track_roll and track_large)

Each marker visible in both views of a frame is triangulated from its ``uv_centroid`` in both cameras (what
a detector finds) with ``triangulate_linear`` and ``triangulate_refracted`` (the dataset's flat stack), and
compared with its labelled ``xyz_mm``. Bins: the frame's indentation depth (the deepest indenter's
``depth_mm``: 0 at rest), and the marker's distance from the left image's centre as a fraction of the half
diagonal. Writes the BENCHMARKS.md section ``triangulation_error`` and docs/figures/triangulation_error.png.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_matching import stack_of_dataset  # noqa: E402
from benchmarks_md import machine_name, update_section  # noqa: E402

from transtac_sim.perception.dataset_files import labelled_images  # noqa: E402
from transtac_sim.perception.stereo import load_calibration  # noqa: E402
from transtac_sim.perception.stereo.triangulation import (  # noqa: E402
    flat_stack_from_dict,
    triangulate_linear,
    triangulate_refracted,
)

REPO = Path(__file__).resolve().parents[1]
DEPTH_BINS = [(-0.01, 0.05, "rest (< 0.05)"), (0.05, 0.5, "0.05-0.5"), (0.5, 1.0, "0.5-1.0"), (1.0, 9.0, ">= 1.0")]
FIELD_BINS = [(0.0, 0.25, "0-0.25"), (0.25, 0.5, "0.25-0.5"), (0.5, 0.75, "0.5-0.75"), (0.75, 1.01, "0.75-1")]


def errors_of(ds: Path) -> dict[str, np.ndarray]:
    calib = load_calibration(ds / "calibration.json")
    stack = flat_stack_from_dict(stack_of_dataset(ds, None)[0])
    w, h = calib.image_size
    half_diag = 0.5 * np.hypot(w, h)
    frames: dict = {}
    for li in labelled_images(ds):
        frames.setdefault((li.sequence, li.frame), {})[li.camera] = li
    out = {k: [] for k in ("linear", "refracted", "depth", "field")}
    for views in frames.values():
        if len(views) < 2:
            continue
        labels = views["left"].labels
        vis = [m for m in labels["markers"] if m["left"]["visible"] and m["right"]["visible"]]
        if not vis:
            continue
        lu = np.array([m["left"]["uv_centroid"] for m in vis])
        ru = np.array([m["right"]["uv_centroid"] for m in vis])
        truth = np.array([m["xyz_mm"] for m in vis])
        out["linear"].append(np.linalg.norm(triangulate_linear(calib, lu, ru) - truth, axis=1))
        out["refracted"].append(np.linalg.norm(triangulate_refracted(calib, stack, lu, ru) - truth, axis=1))
        depth = max([i["depth_mm"] for i in labels["indenters"]], default=0.0)
        out["depth"].append(np.full(len(vis), depth))
        out["field"].append(np.linalg.norm(lu - [(w - 1) / 2, (h - 1) / 2], axis=1) / half_diag)
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}


def _table(e: dict, key: str, bins) -> list[str]:
    rows = []
    for lo, hi, name in bins:
        sel = (e[key] >= lo) & (e[key] < hi)
        if not sel.any():
            continue
        lin, ref = e["linear"][sel], e["refracted"][sel]
        rows.append(f"| {name} | {sel.sum()} | {np.median(ref):.4f} | {np.percentile(ref, 95):.4f} | "
                    f"{np.median(lin):.3f} | {np.percentile(lin, 95):.3f} |")
    return rows


def plot(e: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), dpi=120)
    for ax, key, bins, label in ((axes[0], "depth", DEPTH_BINS, "indentation depth (mm)"),
                                 (axes[1], "field", FIELD_BINS, "distance from the image centre (of the half diagonal)")):
        for kind, style in (("refracted", "C3-o"), ("linear", "k:s")):
            xs, med, p95 = [], [], []
            for lo, hi, _ in bins:
                sel = (e[key] >= lo) & (e[key] < hi)
                if sel.any():
                    xs.append(np.median(e[key][sel]))
                    med.append(np.median(e[kind][sel]))
                    p95.append(np.percentile(e[kind][sel], 95))
            ax.plot(xs, med, style, label=f"{kind}: median")
            ax.plot(xs, p95, style, alpha=0.4, label=f"{kind}: 95th percentile")
        ax.set_yscale("log")
        ax.set_xlabel(label)
        ax.set_ylabel("3D error (mm)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("Triangulated markers vs labelled xyz_mm (exact correspondences)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main(datasets: list[Path] = typer.Argument(None, help="dataset folders (default: datasets/perception_heldout, "
                                                        "track_roll and track_large, those that exist)")) -> None:
    datasets = datasets or [REPO / "datasets" / n for n in ("perception_heldout", "track_roll", "track_large")
                            if (REPO / "datasets" / n).is_dir()]
    parts = [errors_of(ds) for ds in datasets]
    e = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    head = "| mm | refraction-aware median | refraction-aware p95 | linear median | linear p95 |\n| --- | --- | --- | --- | --- | --- |\n"
    md = (f"`python scripts/bench_triangulation_error.py` on {machine_name()}, {time.strftime('%Y-%m-%d')}: "
          f"{', '.join(d.name for d in datasets)}; {len(e['linear'])} markers seen by both cameras, triangulated from "
          "their labelled `uv_centroid` pair, error against `xyz_mm` in mm. Plot: `docs/figures/triangulation_error.png`."
          "\n\nBy indentation depth (deepest indenter, mm):\n\n| depth" + head.replace("| mm ", " | markers ", 1) +
          "\n".join(_table(e, "depth", DEPTH_BINS)) +
          "\n\nBy position in the field of view (distance from the image centre / half diagonal):\n\n| position" +
          head.replace("| mm ", " | markers ", 1) + "\n".join(_table(e, "field", FIELD_BINS)))
    print(md)
    update_section(REPO / "BENCHMARKS.md", "triangulation_error", md)
    plot(e, REPO / "docs" / "figures" / "triangulation_error.png")


if __name__ == "__main__":
    typer.run(main)
