"""Marker detection on the held-out sets, per condition, for the blob baseline and the learned detector
(with and without the correlation term, with and without the centroid refinement), and detection speed.

    .venv/bin/python scripts/bench_detection.py [--models MODEL.pt ...]

Default models: the shipped one (stride-16 context level, no correlation term) and, where they exist, the
variants of README's "Detection and tracking" in out/models/: markernet_context_corr (context + correlation
term), markernet_nocorr and markernet_corr (without the context level, without and with the term).

Held-out data (scripts/make_perception_datasets.sh heldout): datasets/perception_heldout, track_roll and
track_large; their marker layouts, indenters and light differ from the training scenes'. Truth: the visible
markers' ``uv_centroid``. Conditions of an image: ``rest`` (no indenter below the surface), ``press``,
``slide`` or ``roll`` (the trajectory segment of the frame), ``edge`` (only the markers whose rest position
lies within 1 mm of the indenter footprint's outline, and the detections within 4 px of them), and
``leak`` (the contact frames' UV image plus 30 % of the same frame's white-light image). Writes the
BENCHMARKS.md section ``detection_heldout`` (the CPU speed included) and docs/figures/detection_heldout.png.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import typer
from scipy.spatial import ConvexHull

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, update_section  # noqa: E402

from transtac_sim.perception.dataset_files import labelled_images  # noqa: E402
from transtac_sim.perception.detection.blob import detect_blobs  # noqa: E402
from transtac_sim.perception.detection.model_file import DEFAULT_MODEL  # noqa: E402
from transtac_sim.perception.detection.runtime import LearnedDetector  # noqa: E402
from transtac_sim.perception.evaluation.detection import DetectionTally  # noqa: E402
from transtac_sim.perception.images import read_color_image  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
HELDOUT = ["perception_heldout", "track_roll", "track_large"]
CONDITIONS = ["rest", "press", "slide", "roll", "edge", "leak", "all"]
LEAK_FRACTION = 0.3
EDGE_MM = 1.0


def _frame_segments(scene_path: Path) -> list[str]:
    from transtac_sim.config import load_scene

    segs = load_scene(scene_path).indenters[0].trajectory
    return [s.kind for s in segs for _ in range(s.frames)]


def _footprint_outline(li, setup_cache: dict) -> tuple[np.ndarray, float] | None:
    """The xy outline (left camera frame, mm) of the indenter part below the undeformed contact surface,
    or None without contact."""
    from transtac_sim.config import load_scene
    from transtac_sim.dataset.randomize import sequence_variant
    from transtac_sim.scene_setup import build_setup

    scene_path = REPO / "scenes" / "perception" / f"{li.dataset.name}.toml"
    key = (li.dataset.name, li.sequence)
    if key not in setup_cache:
        scene = load_scene(scene_path)
        var = sequence_variant(scene, int(li.sequence.split("_")[-1]))
        setup_cache[key] = build_setup(var.scene, scene_path, marker_seed=var.marker_seed)
    setup = setup_cache[key]
    ind = li.labels["indenters"][0]
    if ind["depth_mm"] <= 0:
        return None
    v = setup.indenters[0].mesh.mesh.vertices
    pose = np.asarray(ind["pose_mm"])
    x = v @ pose[:3, :3].T + pose[:3, 3]
    surface_z = setup.sensor.gel_origin_in_left_mm[2] + setup.sensor.gel_size_mm[2]
    below = x[x[:, 2] < surface_z][:, :2]
    if len(below) < 3:
        return None
    return below[ConvexHull(below).vertices]


def _distance_to_outline(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    a, b = poly, np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(((p[:, None] - a[None]) * ab[None]).sum(2) / (ab**2).sum(1)[None], 0, 1)
    return np.linalg.norm(p[:, None] - (a[None] + t[..., None] * ab[None]), axis=2).min(1)


def _images(datasets: list[Path]):
    """(condition list, image, truth uv, edge mask or None) for every held-out image; leak copies included."""
    cache: dict = {}
    for ds in datasets:
        kinds = _frame_segments(REPO / "scenes" / "perception" / f"{ds.name}.toml")
        for li in labelled_images(ds):
            img = read_color_image(li.uv_path)
            depth = li.labels["indenters"][0]["depth_mm"] if li.labels["indenters"] else 0.0
            kind = "rest" if depth <= 0 else {"hold": "press", "release": "press"}.get(kinds[li.frame], kinds[li.frame])
            outline = _footprint_outline(li, cache) if depth > 0 else None
            edge = None
            if outline is not None:
                rest = {m["id"]: m["xyz_rest_mm"][:2] for m in li.labels["markers"]}
                edge = _distance_to_outline(np.array([rest[i] for i in li.truth.ids]).reshape(-1, 2), outline) <= EDGE_MM
            yield [kind], img, li.truth.uv, edge
            if depth > 0 and li.white_path is not None:
                white = read_color_image(li.white_path).astype(np.float32)
                leak = np.clip(np.rint(img + LEAK_FRACTION * white), 0, 255).astype(np.uint8)
                yield ["leak"], leak, li.truth.uv, None


def main(models: list[Path] = typer.Option([DEFAULT_MODEL, REPO / "out/models/markernet_context_corr.pt",
                                            REPO / "out/models/markernet_nocorr.pt", REPO / "out/models/markernet_corr.pt"]),
         datasets_root: Path = typer.Option(REPO / "datasets"), write: bool = typer.Option(True),
         figure: Path = typer.Option(REPO / "docs" / "figures" / "detection_heldout.png")) -> None:
    datasets = [datasets_root / n for n in HELDOUT if (datasets_root / n).is_dir()]
    methods: dict[str, object] = {"blob": lambda im: detect_blobs(im)}
    for m in [m for m in models if m.is_file()]:
        tag = "learned (shipped)" if m == DEFAULT_MODEL else f"learned: {m.stem.removeprefix('markernet_')}"
        for refine in (True, False) if m == DEFAULT_MODEL else (True,):
            det = LearnedDetector(m, device="cpu", refine=refine)
            methods[f"{tag}{'' if refine else ' (offset head only)'}"] = (lambda d: lambda im: d.detect([im])[0])(det)
    tallies = {name: {c: DetectionTally() for c in CONDITIONS} for name in methods}
    seconds = {name: [] for name in methods}
    n_images = 0
    for conds, img, truth, edge in _images(datasets):
        n_images += 1
        for name, fn in methods.items():
            t0 = time.perf_counter()
            det = fn(img)
            seconds[name].append(time.perf_counter() - t0)
            for c in conds + ["all"]:
                tallies[name][c].add(det.uv, truth)
            if edge is not None and edge.any():
                near = np.linalg.norm(det.uv[:, None] - truth[edge][None], axis=2).min(1) <= 4.0 if len(det.uv) else np.zeros(0, bool)
                tallies[name]["edge"].add(det.uv[near], truth[edge])
    rows = []
    for name in methods:
        for c in CONDITIONS:
            s = tallies[name][c].summary()
            if s["images_truths"] == 0:
                continue
            rows.append(f"| {name} | {c} | {s['images_truths']} | {s['precision@1px']:.4f} | {s['recall@1px']:.4f} | "
                        f"{s['f1@1px']:.4f} | {s['precision@2px']:.4f} | {s['recall@2px']:.4f} | {s['f1@2px']:.4f} | "
                        f"{s['error_median_px']:.3f} | {s['error_p95_px']:.3f} |")
    speed = [f"| {name} | {1000 * np.median(t):.1f} | {1 / (2 * np.median(t)):.1f} |" for name, t in seconds.items()]
    md = (f"`python scripts/bench_detection.py` on {machine_name()}, {time.strftime('%Y-%m-%d')}: {n_images} held-out "
          f"images ({', '.join(d.name for d in datasets)}; leak = UV + {LEAK_FRACTION:g} x white), truth `uv_centroid`.\n\n"
          "| method | condition | true markers | P@1px | R@1px | F1@1px | P@2px | R@2px | F1@2px | median err px | p95 err px |\n"
          "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |\n" + "\n".join(rows) +
          "\n\nSpeed on this machine, one image at a time (learned: onnxruntime; the stereo-pair rate is half the image rate):\n\n"
          "| method | ms per image (median) | stereo pairs per second |\n| --- | --- | --- |\n" + "\n".join(speed))
    print(md)
    if write:
        update_section(REPO / "BENCHMARKS.md", "detection_heldout", md)
        _plot(tallies, figure)


def _plot(tallies: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(tallies)
    conds = [c for c in CONDITIONS if tallies[names[0]][c].truths]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    w = 0.8 / len(names)
    for k, name in enumerate(names):
        s = [tallies[name][c].summary() for c in conds]
        axes[0].bar(np.arange(len(conds)) + k * w, [x["f1@2px"] for x in s], w, label=name)
        axes[1].bar(np.arange(len(conds)) + k * w, [x["error_median_px"] for x in s], w, label=name)
    for ax, title in zip(axes, ["F1 at 2 px", "median localisation error (px)"], strict=True):
        ax.set_xticks(np.arange(len(conds)) + 0.4 - w / 2, conds)
        ax.set_title(title)
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylim(0.5, 1.0)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle("Marker detection on the held-out sets (layout, indenter and light differ from training)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    typer.run(main)
