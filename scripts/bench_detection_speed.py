"""Detection speed for stereo pairs (both 640x480 UV images in one batch), with the time split into
pre-processing, network and decoding (decode includes the centroid refinement).

    .venv/bin/python scripts/bench_detection_speed.py [--device cpu|cuda] [--pairs 50]

CPU: the learned detector through onnxruntime (the default there) and the blob baseline. CUDA: the learned
detector through PyTorch with every step on the GPU, in float32 and under float16 autocast. Images: the
left/right UV pairs of datasets/perception_heldout. Writes the BENCHMARKS.md section
``detection_speed_cpu`` or ``detection_speed_gpu``.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import typer

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmarks_md import machine_name, publish  # noqa: E402

from transtac_sim.perception.detection.blob import detect_blobs  # noqa: E402
from transtac_sim.perception.detection.model_file import DEFAULT_MODEL  # noqa: E402
from transtac_sim.perception.detection.runtime import LearnedDetector  # noqa: E402
from transtac_sim.perception.images import read_color_image  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def _pairs(root: Path, n: int) -> list[list[np.ndarray]]:
    lefts = sorted(root.glob("sequences/*/*/left_uv.png"))[:n]
    return [[read_color_image(p), read_color_image(p.with_name("right_uv.png"))] for p in lefts]


def _time(detect, pairs, repeats: int) -> tuple[float, dict]:
    for p in pairs[:3]:
        detect(p)  # warm-up (kernel compilation, allocator)
    walls, split = [], {}
    for _ in range(repeats):
        for p in pairs:
            t0 = time.perf_counter()
            out = detect(p)
            walls.append(time.perf_counter() - t0)
            for k, v in out[0].seconds.items():
                split.setdefault(k, []).append(v)
    return float(np.median(walls)), {k: float(np.median(v)) for k, v in split.items()}


def main(device: str = typer.Option("cpu"), pairs: int = typer.Option(20, min=1), repeats: int = typer.Option(3, min=1),
         model: Path = typer.Option(DEFAULT_MODEL), images: Path = typer.Option(REPO / "datasets/perception_heldout"),
         write: bool = typer.Option(True), md_out: Path = typer.Option(None, help="also write the table to this file")) -> None:
    data = _pairs(images, pairs)
    rows = []
    if device == "cpu":
        runs = {"learned (onnxruntime)": LearnedDetector(model, device="cpu", backend="onnx").detect,
                "blob": lambda p: [detect_blobs(im) for im in p]}
        where = machine_name("cpu")
    else:
        det = LearnedDetector(model, device=device, backend="torch")
        runs = {"learned (PyTorch, float32)": det.detect}
        half = LearnedDetector(model, device=device, backend="torch")
        half.net = half.net.to(memory_format=torch.channels_last)

        def detect_half(p, d=half):
            with torch.autocast("cuda", dtype=torch.float16):
                return d.detect(p)

        runs["learned (PyTorch, float16)"] = detect_half
        where = f"GPU {torch.cuda.get_device_name()}"
    for name, fn in runs.items():
        wall, split = _time(fn, data, repeats)
        rows.append(f"| {name} | {1000 * wall:.2f} | {1 / wall:.1f} | " + ", ".join(f"{k} {1000 * v:.2f}" for k, v in split.items()) + " |")
    load = f", load average {os.getloadavg()[0]:.1f} at the end" if device == "cpu" else ""
    md = (f"`python scripts/bench_detection_speed.py --device {device}` on {where} (torch {torch.__version__}{load}), "
          f"{time.strftime('%Y-%m-%d')}: {len(data)} stereo pairs of 640x480 UV images x {repeats}, medians.\n\n"
          "| detector | ms per stereo pair | stereo pairs per second | split (ms) |\n| --- | --- | --- | --- |\n" + "\n".join(rows))
    publish(md, md_out, write, f"detection_speed_{'cpu' if device == 'cpu' else 'gpu'}")


if __name__ == "__main__":
    typer.run(main)
