"""Render error against runtime: sweep samples per pixel (as the sampler rounds them), resolution and maximum path depth, and measure
seconds per stereo frame (2 cameras x UV + white) against (a) the image error relative to a converged
reference and (b) the error of the markers' UV intensity centroids; table + PNG with the Pareto front.

    .venv/bin/python scripts/render_error_vs_runtime.py [--quick] [--variant cuda_ad_rgb] [--no-write]

Scene: ``demo_scene`` with a sphere indenter pressed 1 mm in. Image error: RMSE of the linear recorded
image against the reference, in % of the reference's 99.5th-percentile level, mean of the 4 images
(half-resolution renders are upscaled with cv2.resize first). Centroid error: median and 95th percentile
over markers of |uv_centroid - uv_centroid of the reference|. The reference (native resolution, many
spp, depth 12) is rendered twice with different seeds: their difference / sqrt(2) is its own noise floor.
Timing: the second of two renders of each setting (the first compiles). Sampler: ``RenderSettings().sampler``. Writes BENCHMARKS.md section
``render_error_vs_runtime`` and docs/figures/render_error_vs_runtime.png unless --no-write.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import update_section  # noqa: E402

from transtac_sim.camera.model import CameraEffects  # noqa: E402
from transtac_sim.labels.markers import frame_labels  # noqa: E402
from transtac_sim.rendering import demo_scene  # noqa: E402
from transtac_sim.rendering.benchmarks import machine, markdown_table  # noqa: E402
from transtac_sim.rendering.inputs import RenderRequest, RenderSettings  # noqa: E402
from transtac_sim.rendering.renderer import Renderer  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
IDEAL = CameraEffects(noise=False, quantize=False)


def stereo_frame(size, spp, max_depth, variant, seed, repeats=1):
    """(linear images, uv centroids per camera, seconds of the last repeat) of one stereo frame."""
    scene = demo_scene.sensor_scene(size=size, indenters=[demo_scene.indenter_sphere()])
    frame = demo_scene.indented_frame(scene, 1.0)
    r = Renderer(scene, RenderRequest(), RenderSettings(spp=spp, max_depth=max_depth, variant=variant), IDEAL)
    for i in range(repeats):
        t = time.perf_counter()
        out = r.render(frame, seed=seed + i)
        seconds = time.perf_counter() - t
    labels = frame_labels(scene, frame, {c: m.recorded for c, m in r.cameras.items()},
                          {c: out.linear[(c, "uv")] for c in r.cameras})
    return (out.linear, {c: np.where(lab.visible[:, None], lab.uv_centroid, np.nan) for c, lab in labels.items()}, seconds,
            r.variant, r.spp)


def image_error(imgs, ref, size):
    errs = {}
    for k, img in imgs.items():
        if img.shape[:2] != ref[k].shape[:2]:
            img = cv2.resize(img, size, interpolation=cv2.INTER_LINEAR)
        errs[k] = 100 * np.sqrt(np.mean((img - ref[k]) ** 2)) / np.percentile(ref[k], 99.5)
    return float(np.mean(list(errs.values()))), errs


def centroid_error(cen, ref_cen, scale):
    """Centroids of an image ``scale`` times the reference's size, compared in the reference's pixels (centre of
    the top-left pixel at 0 in both: u_ref = (u + 0.5) / scale - 0.5)."""
    d = np.concatenate([np.linalg.norm((cen[c] + 0.5) / scale - 0.5 - ref_cen[c], axis=1) for c in ref_cen])
    d = d[np.isfinite(d)]
    return float(np.median(d)), float(np.percentile(d, 95)), len(d)


def pareto(points):
    """Indices of points (seconds, error) that no other point beats in both."""
    return [i for i, (t, e) in enumerate(points)
            if not any((t2 <= t and e2 <= e) and (t2 < t or e2 < e) for t2, e2 in points)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", default=None)
    ap.add_argument("--quick", action="store_true", help="320x240 native (~5 min on 2 CPU cores; 640x480 takes ~4x)")
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    size = (320, 240) if a.quick else (640, 480)
    spps = [1, 4, 16, 32]
    depths = [3, 5, 8]
    scales = [1.0, 0.5]
    ref_spp = 256 if a.quick else 128

    t0 = time.perf_counter()
    ref, ref_cen, _, variant, ref_spp = stereo_frame(size, ref_spp, 12, a.variant, seed=1000)
    ref2, ref2_cen, _, _, _ = stereo_frame(size, ref_spp, 12, a.variant, seed=2000)
    floor = image_error(ref2, ref, size)[0] / np.sqrt(2)
    floor_c = [x / np.sqrt(2) for x in centroid_error(ref2_cen, ref_cen, 1.0)[:2]]
    print(f"reference: {time.perf_counter() - t0:.0f} s, noise floor {floor:.3f} %, centroid {floor_c}", flush=True)

    rows = []
    for spp, depth, scale in itertools.product(spps, depths, scales):
        sub = (int(size[0] * scale), int(size[1] * scale))
        imgs, cen, sec, _, spp_used = stereo_frame(sub, spp, depth, a.variant, seed=7, repeats=2)
        err, per = image_error(imgs, ref, size)
        c_med, c_p95, n = centroid_error(cen, ref_cen, scale)
        rows.append([spp_used, depth, f"{sub[0]}x{sub[1]}", sec, err, per[("left", "uv")], per[("left", "white")], c_med, c_p95, n])
        print(rows[-1], flush=True)

    front = set(pareto([(r[3], r[4]) for r in rows]))
    header = ["spp", "max depth", "resolution", "s / stereo frame", "image err %", "UV err % (left)",
              "white err % (left)", "centroid err median px", "centroid err p95 px", "markers", "Pareto"]
    table = markdown_table(header, [r + ["*" if i in front else ""] for i, r in enumerate(rows)])
    # default: the fastest native-resolution setting whose marker centroids are within 0.1 px (p95) of the
    # reference's and whose image error is within 1.5x of the best native one
    native = [r for r in rows if r[2] == f"{size[0]}x{size[1]}"]
    best = min(r[4] for r in native)
    ok = [r for r in native if r[8] <= 0.1 and r[4] <= 1.5 * best]
    choice = min(ok, key=lambda r: r[3]) if ok else None

    if not a.no_write:
        import matplotlib
        import matplotlib.ticker

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=80)
        for ax, col, label in ((axes[0], 4, "image RMSE (% of ref. level)"), (axes[1], 8, "centroid error p95 (px)")):
            for depth, c in zip(depths, plt.cm.viridis(np.linspace(0, 0.9, len(depths))), strict=True):
                for scale, m in zip(scales, "os", strict=True):
                    pts = [(r[3], r[col]) for r in rows if r[1] == depth and r[2] == f"{int(size[0] * scale)}x{int(size[1] * scale)}"]
                    ax.plot(*zip(*pts, strict=True), m + "-", color=c, ms=4, lw=0.8,
                            label=f"depth {depth}, {'native' if scale == 1 else 'half'} res")
            if col == 4:
                f = sorted((rows[i][3], rows[i][4]) for i in front)
                ax.plot(*zip(*f, strict=True), "k--", lw=1.2, label="Pareto front")
                ax.axhline(floor, color="grey", lw=0.8, ls=":", label="reference noise")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
            ax.set_xlabel("seconds per stereo frame")
            ax.set_ylabel(label)
            ax.grid(alpha=0.3, which="both")
        axes[0].legend(fontsize=6)
        fig.suptitle(f"{size[0]}x{size[1]}, {machine(variant)}, {variant}", fontsize=9)
        fig.tight_layout()
        out = REPO / "docs" / "figures" / "render_error_vs_runtime.png"
        out.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out)
    cmd = "python scripts/render_error_vs_runtime.py " + " ".join(sys.argv[1:])
    chosen = (f"Chosen (fastest native-resolution setting with image error within 1.5x of the best native one and "
              f"centroid p95 <= 0.1 px): **{choice[0]} spp, max depth {choice[1]}** ({choice[3]:.2f} s, "
              f"{choice[4]:.2f} %, centroid p95 {choice[8]:.3f} px)." if choice else "No setting met the criteria.")
    body = (f"Machine: {machine(variant)}, variant `{variant}`; native {size[0]}x{size[1]}; reference {ref_spp} spp, "
            f"depth 12 (noise floor: image {floor:.3f} %, centroid median/p95 {floor_c[0]:.3f}/{floor_c[1]:.3f} px).\n"
            f"Command: `{cmd.strip()}`\n\n{table}\n\n{chosen}\n\n![](docs/figures/render_error_vs_runtime.png)")
    print(body)
    if not a.no_write:
        update_section(REPO / "BENCHMARKS.md", "render_error_vs_runtime" + ("" if variant.startswith("llvm") else "_gpu"), body)


if __name__ == "__main__":
    main()
