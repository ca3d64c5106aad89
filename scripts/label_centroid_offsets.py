"""How far the rendered blob centroid of a real-size marker lies from its exact label ``uv`` across the
field of both cameras: table by field angle + PNG.

    .venv/bin/python scripts/label_centroid_offsets.py [--quick] [--variant cuda_ad_rgb] [--no-write]

Scene: ``demo_scene`` (markers r = 0.25 mm, 0.5 mm under the contact face, jittered 2.5 mm grid), flat
and under a 1.5 mm Gaussian indentation; noise-free UV renders (no camera noise, many spp) at the default
path depth and at depth 3 (the direct refracted image only, no ghost reflections). Offset = uv_centroid -
uv; "radial" is its component away from the principal point (positive: outwards). Writes BENCHMARKS.md
section ``label_centroid_offsets`` and docs/figures/label_centroid_offsets.png unless --no-write.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import update_section  # noqa: E402

from transtac_sim.camera.model import CameraEffects  # noqa: E402
from transtac_sim.labels.markers import frame_labels  # noqa: E402
from transtac_sim.rendering import demo_scene  # noqa: E402
from transtac_sim.rendering.benchmarks import machine, markdown_table  # noqa: E402
from transtac_sim.rendering.inputs import FrameState, RenderRequest, RenderSettings  # noqa: E402
from transtac_sim.rendering.renderer import Renderer  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
BINS = [0, 15, 30, 40, 50, 90]


def offsets(size, spp, depth, indent_mm, variant):
    """Per camera: (field angle deg, offset (K, 2) px, radial offset px) of the visible markers."""
    scene = demo_scene.sensor_scene(size=size)
    frame = demo_scene.indented_frame(scene, indent_mm, centre_xy=(2.0, 1.0), sigma_mm=2.5) if indent_mm else FrameState()
    r = Renderer(scene, RenderRequest(illuminations=("uv",)), RenderSettings(spp=spp, max_depth=depth, variant=variant),
                 CameraEffects(noise=False, quantize=False))
    out = r.render(frame, seed=3)
    labels = frame_labels(scene, frame, {c: m.recorded for c, m in r.cameras.items()},
                          {c: out.linear[(c, "uv")] for c in r.cameras})
    res = {}
    for cam, lab in labels.items():
        ok = lab.visible & np.isfinite(lab.uv_centroid).all(axis=1)
        K = r.cameras[cam].spec.K
        xy = (lab.uv[ok] - K[:2, 2]) / np.diag(K)[:2]
        angle = np.degrees(np.arctan(np.linalg.norm(xy, axis=1)))
        d = lab.uv_centroid[ok] - lab.uv[ok]
        e = (lab.uv[ok] - K[:2, 2]) / np.maximum(np.linalg.norm(lab.uv[ok] - K[:2, 2], axis=1, keepdims=True), 1e-9)
        res[cam] = (angle, d, (d * e).sum(axis=1), lab.uv[ok])
    return res, r.variant


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", default=None)
    ap.add_argument("--quick", action="store_true", help="320x240 instead of 640x480 (~3 min on 2 CPU cores)")
    ap.add_argument("--spp", type=int, default=None)
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args()
    size = (320, 240) if a.quick else (640, 480)
    spp = a.spp or 64
    default_depth = RenderSettings().max_depth
    t0 = time.perf_counter()
    runs = {}
    for depth in (default_depth, 3):
        for indent in (0.0, 1.5):
            runs[(depth, indent)], variant = offsets(size, spp, depth, indent, a.variant)
            print(f"depth {depth}, indentation {indent} mm: {time.perf_counter() - t0:.0f} s", flush=True)
    rows = []
    for (depth, indent), res in runs.items():
        for cam, (angle, d, radial, _) in res.items():
            n = np.linalg.norm(d, axis=1)
            for lo, hi in zip(BINS[:-1], BINS[1:], strict=True):
                m = (angle >= lo) & (angle < hi)
                if m.any():
                    rows.append([depth, indent, cam, f"{lo}-{hi}", int(m.sum()), float(np.median(n[m])),
                                 float(np.percentile(n[m], 95)), float(n[m].max()), float(np.mean(radial[m]))])
    header = ["max depth", "indent mm", "camera", "field angle deg", "markers", "|offset| median px", "p95 px",
              "max px", "mean radial px"]
    table = markdown_table(header, rows)
    if not a.no_write:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), dpi=80)
        angle, d, radial, uv = runs[(default_depth, 0.0)]["left"]
        axes[0].quiver(uv[:, 0], uv[:, 1], d[:, 0], d[:, 1], angles="xy", scale_units="xy", scale=1 / 100, width=0.004)
        axes[0].set_xlim(0, size[0])
        axes[0].set_ylim(size[1], 0)
        axes[0].set_aspect("equal")
        axes[0].set_title(f"left camera, offsets x100 (depth {default_depth}, flat)", fontsize=8)
        for (depth, indent), res in runs.items():
            ang = np.concatenate([res[c][0] for c in res])
            n = np.concatenate([np.linalg.norm(res[c][1], axis=1) for c in res])
            axes[1].plot(ang, n, "o" if depth == 3 else ".", ms=3, alpha=0.6, mfc="none" if indent else None,
                         label=f"depth {depth}, indent {indent} mm")
        axes[1].set_xlabel("field angle (deg)")
        axes[1].set_ylabel("|uv_centroid - uv| (px)")
        axes[1].legend(fontsize=6)
        axes[1].grid(alpha=0.3)
        fig.suptitle(f"{size[0]}x{size[1]}, r = 0.25 mm, {spp} spp, {machine(variant)}", fontsize=9)
        fig.tight_layout()
        fig.savefig(REPO / "docs" / "figures" / "label_centroid_offsets.png")
    cmd = "python scripts/label_centroid_offsets.py " + " ".join(sys.argv[1:])
    body = (f"Machine: {machine(variant)}, variant `{variant}`; {size[0]}x{size[1]}, marker radius 0.25 mm, {spp} spp, "
            f"noise-free UV renders, both cameras; {time.perf_counter() - t0:.0f} s.\nCommand: `{cmd.strip()}`\n\n{table}"
            "\n\n![](docs/figures/label_centroid_offsets.png)")
    print(body)
    if not a.no_write:
        update_section(REPO / "BENCHMARKS.md", "label_centroid_offsets", body)


if __name__ == "__main__":
    main()
