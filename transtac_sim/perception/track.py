"""``transtac-sim track``: markers tracked over a sequence of UV images (a folder of frames in name order,
or one camera of one sequence of a dataset). Output (JSON, written atomically once every frame is done):

    {"method": str, "detector": str, "model": str | null,
     "frames": [{"frame": int, "path": str,
                 "markers": [{"uv": [u, v], "track_id": int, "displacement_px": [du, dv] | null}]}]}

``track_id`` is -1 for a detection no track took; ``displacement_px`` is the move from where the track
was first seen.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from transtac_sim.perception.detect import make_detector
from transtac_sim.perception.errors import PerceptionInputError, output_file
from transtac_sim.perception.images import find_images, is_dataset, read_color_image, sequence_files
from transtac_sim.perception.tracking.bytetrack import track_bytetrack
from transtac_sim.perception.tracking.flow import track_flow
from transtac_sim.writer.atomic import write_json


@dataclass
class TrackReport:
    out: Path
    frames: int
    tracks: int
    seconds: dict[str, float]


def sequence_images(target: Path, sequence: str | None, camera: str) -> list:
    """The frames to track: a folder's images, or ``<camera>_uv.png`` of each complete frame of a dataset's
    sequence (images.py ``sequence_files``)."""
    target = Path(target)
    if target.is_dir() and is_dataset(target):
        return [refs[0] for refs in sequence_files(target, sequence, (f"{camera}_uv.png",))]
    return find_images(target)


def track_images(target: Path, out: Path, method: str = "bytetrack", detector: str = "learned",
                 model: Path | None = None, sequence: str | None = None, camera: str = "left",
                 device: str = "auto", progress: Callable[[int, int], None] | None = None) -> TrackReport:
    if method not in ("bytetrack", "flow"):
        raise ValueError(f"unknown tracking method {method!r} (bytetrack or flow)")
    if camera not in ("left", "right"):
        raise ValueError(f"unknown camera {camera!r} (left or right)")
    out = output_file(out)
    refs = sequence_images(target, sequence, camera)
    images = [read_color_image(r.path) for r in refs]
    for r, im in zip(refs, images, strict=True):  # one camera's frames: one size
        if im.shape != images[0].shape:
            raise PerceptionInputError(r.path, f"image is {im.shape[1]}x{im.shape[0]} px, the first frame "
                                       f"{images[0].shape[1]}x{images[0].shape[0]}",
                                       "track frames of one camera (one image size)")
    detect, model_name = make_detector(detector, model, device, images=[(str(r.path), im) for r, im in zip(refs, images, strict=True)])
    t0 = time.perf_counter()
    frames = []
    for i, im in enumerate(images):
        frames.append(detect([im])[0])
        if progress:
            progress(i + 1, len(images))
    t1 = time.perf_counter()
    result = track_bytetrack(frames) if method == "bytetrack" else track_flow(frames, images)
    t2 = time.perf_counter()
    entries = result.as_json()
    for e, r in zip(entries, refs, strict=True):
        e["path"] = r.name
    write_json(Path(out), {"method": method, "detector": detector, "model": model_name, "frames": entries})
    n_tracks = len({int(t) for ids in result.track_ids for t in ids if t >= 0})
    return TrackReport(Path(out), len(refs), n_tracks, {"detect": t1 - t0, "track": t2 - t1})
