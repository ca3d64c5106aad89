"""Seconds per full stereo frame: both cameras x UV and white light, at native resolution and the default
samples per pixel, on the representative sensor of ``transtac_sim.rendering.demo_scene`` with a sphere
indenter pressed a little deeper every frame (gel, markers and indenter updated in place).

    .venv/bin/python scripts/bench_render.py [--variant cuda_ad_rgb] [--frames 5] [--quick] [--no-write]

Reports the first frame (Dr.Jit compiles its kernels then) apart from the median of the next frames, split
into scene update, render (incl. the lens-distortion remap), camera model (8-bit) and labels (incl. the
UV centroids); writes the table into BENCHMARKS.md (section ``bench_render``) unless --no-write.
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
from transtac_sim.rendering.inputs import RenderRequest, RenderSettings  # noqa: E402
from transtac_sim.rendering.renderer import Renderer  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variant", default=None, help="Mitsuba variant (default: cuda_ad_rgb if a GPU, else llvm_ad_rgb)")
    ap.add_argument("--spp", type=int, default=RenderSettings().spp)
    ap.add_argument("--max-depth", type=int, default=RenderSettings().max_depth)
    ap.add_argument("--frames", type=int, default=5, help="timed frames after the first")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--quick", action="store_true", help="2 timed frames")
    ap.add_argument("--no-write", action="store_true", help="do not update BENCHMARKS.md")
    a = ap.parse_args()
    frames = 2 if a.quick else a.frames
    size = tuple(int(x) for x in a.size.split("x"))

    t = time.perf_counter()
    scene = demo_scene.sensor_scene(size=size, indenters=[demo_scene.indenter_sphere()])
    r = Renderer(scene, RenderRequest(("left", "right"), ("uv", "white")),
                 RenderSettings(spp=a.spp, max_depth=a.max_depth, variant=a.variant), CameraEffects())
    t_build = time.perf_counter() - t
    specs = {c: m.recorded for c, m in r.cameras.items()}
    rows = []
    for i in range(frames + 1):
        frame = demo_scene.indented_frame(scene, 0.5 + 0.2 * i)
        t0 = time.perf_counter()
        out = r.render(frame, seed=i)
        t1 = time.perf_counter()
        r.to_8bit(out, seed=i)
        t2 = time.perf_counter()
        frame_labels(scene, frame, specs, {c: out.linear[(c, "uv")] for c in specs})
        t3 = time.perf_counter()
        rows.append([out.seconds["update"], out.seconds["render"], t2 - t1, t3 - t2, t1 - t0, t3 - t0])
        print(f"frame {i}: render {t1 - t0:.3f} s, with camera + labels {t3 - t0:.3f} s", flush=True)
    rows = np.array(rows)
    med = np.median(rows[1:], axis=0)
    names = ["scene update", "render 2 cameras x (UV + white)", "camera model (8-bit)", "labels (+ UV centroids)",
             "frame without labels/camera", "full frame"]
    table = markdown_table(["stage", "first frame (s)", f"median of {frames} next frames (s)"],
                           [[n, float(f), float(m)] for n, f, m in zip(names, rows[0], med, strict=True)])
    cmd = "python scripts/bench_render.py " + " ".join(sys.argv[1:])
    body = (f"Full stereo frame: {size[0]}x{size[1]}, {a.spp} spp, max depth {a.max_depth}, variant `{r.variant}`, "
            f"{len(scene.markers.centres)} markers, sphere indenter; machine: {machine(r.variant)}; scene build "
            f"{t_build:.2f} s.\nCommand: `{cmd.strip()}`\n\n{table}")
    print(body)
    if not a.no_write:
        update_section(REPO / "BENCHMARKS.md", "bench_render" + ("" if r.variant.startswith("llvm") else "_gpu"), body)


if __name__ == "__main__":
    main()
