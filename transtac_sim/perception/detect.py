"""``transtac-sim detect``: markers in an image, a folder of images or a dataset's UV images, written as the
pipeline's detection file (DESIGN.md section 6; ``docs/formats.md``):

    {"method": str, "model": str | null,
     "images": [{"path": str, "markers": [{"uv": [u, v], "score": float}]}]}

Every image is read and checked before anything is written, and the file is written atomically: a bad
image stops the run with one line naming it and leaves no output file.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from transtac_sim.perception.detection import Detections
from transtac_sim.perception.detection.blob import detect_blobs
from transtac_sim.perception.errors import output_file
from transtac_sim.perception.images import find_images, read_color_image
from transtac_sim.writer.atomic import write_json


@dataclass
class DetectReport:
    out: Path
    preview: Path | None
    method: str
    model: str | None
    images: int
    markers: int
    seconds: dict[str, float] = field(default_factory=dict)  # per stage, summed over images
    wall_seconds: float = 0.0


def make_detector(method: str, model: Path | None = None, device: str = "auto", refine: bool = True,
                  images: list[tuple[str, np.ndarray]] = ()) -> tuple[Callable[[list], list[Detections]], str | None]:
    """A function detecting markers in a batch of images, and the model path it uses (None for blob).
    ``images`` (name, image) are checked first: a size the learned model was not trained on raises
    PerceptionInputError naming the image."""
    if method == "blob":
        return (lambda batch: [detect_blobs(im) for im in batch]), None
    if method != "learned":
        raise ValueError(f"unknown detection method {method!r} (learned or blob)")
    from transtac_sim.perception.detection.runtime import LearnedDetector

    det = LearnedDetector(model, device=device, refine=refine)
    for name, image in images:
        det.check_size(image, name)
    return det.detect, str(det.model_path)


def detect_images(target: Path, out: Path, method: str = "learned", model: Path | None = None,
                  device: str = "auto", refine: bool = True, preview: Path | None = None,
                  progress: Callable[[int, int], None] | None = None) -> DetectReport:
    """Detect, write ``out`` and, if asked, ``preview`` (the first image with its markers circled)."""
    t0 = time.perf_counter()
    out = output_file(out)
    refs = find_images(Path(target))
    images = [read_color_image(r.path) for r in refs]  # all checked before any work
    detect, model_name = make_detector(method, model, device, refine,
                                       [(str(r.path), im) for r, im in zip(refs, images, strict=True)])
    entries, seconds, total, first = [], {}, 0, None
    for i, (ref, im) in enumerate(zip(refs, images, strict=True)):
        d = detect([im])[0]
        for k, v in d.seconds.items():
            seconds[k] = seconds.get(k, 0.0) + v
        entries.append({"path": ref.name, "markers": d.as_json()})
        first = d if first is None else first  # not `or`: a Detections with no markers is falsy
        total += len(d)
        if progress:
            progress(i + 1, len(refs))
    write_json(Path(out), {"method": method, "model": model_name, "images": entries})
    if preview:
        from transtac_sim.perception.preview import detection_preview

        detection_preview(images[0], first.uv, preview)
    return DetectReport(Path(out), preview, method, model_name, len(refs), total, seconds, time.perf_counter() - t0)
