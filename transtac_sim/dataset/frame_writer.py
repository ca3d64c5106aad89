"""Writing one frame of the dataset: images (8-bit PNG), depth (float32 EXR, mm), then labels.json last.

Every file is written atomically; ``labels.json`` going in last is what marks the frame complete, as long as it
parses and every image the scene asks for is there, whole (a dataset damaged later, e.g. a file deleted or cut short
by a copy, has its damaged frames written again on resume).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.config.scene import Outputs
from transtac_sim.dataset import contract
from transtac_sim.writer.atomic import atomic_write, write_json


@dataclass
class FrameOutput:
    """Everything one frame writes. Images are (H, W, 3) uint8 RGB; depth (H, W) float32 mm."""

    sequence: str
    frame: int
    labels: dict
    images: dict[tuple[str, str], np.ndarray] = field(default_factory=dict)  # (camera, illumination) -> RGB
    depth: dict[str, np.ndarray] = field(default_factory=dict)  # camera -> z-depth mm


def encode_png(rgb: np.ndarray) -> bytes:
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 RGB image, got {rgb.dtype} {rgb.shape}")
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 6])
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def write_exr_depth(path: Path, depth_mm: np.ndarray) -> Path:
    """Single-channel float32 EXR named ``Z`` (mm); pixels with no surface hold +inf."""
    import OpenEXR

    def write(f):
        OpenEXR.File({"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION},
                     {"Z": np.ascontiguousarray(depth_mm, dtype=np.float32)}).write(f)

    return atomic_write(path, write)


def write_frame(root: Path, out: FrameOutput) -> Path:
    """Write ``out`` into its folder of the dataset at ``root``; returns the labels.json path."""
    return write_frame_files(contract.frame_dir(root, out.sequence, out.frame), out)


def write_frame_files(d: Path, out: FrameOutput) -> Path:
    """Images, depth, then labels.json (last: it marks the frame complete) into folder ``d``."""
    for (cam, ill), rgb in sorted(out.images.items()):
        data = encode_png(rgb)
        atomic_write(d / contract.image_name(cam, ill), lambda f, data=data: f.write(data))
    for cam, z in sorted(out.depth.items()):
        write_exr_depth(d / contract.depth_name(cam), z)
    return write_json(d / "labels.json", out.labels)


PNG_END = b"IEND\xaeB`\x82"  # the last chunk of every PNG: its type and CRC
LABELS_MISSING = "labels.json missing"  # the frame was not finished (``frame_problems``)


def frame_problems(root: Path, sequence: str, frame: int, outputs: Outputs | None = None) -> list[str]:
    """Why one frame of the dataset at ``root`` is not complete; [] when it is. ``labels.json`` absent (the frame
    was not finished) or unreadable; given the scene's ``outputs``, also each image and depth file it asks for that
    is absent, empty or, for a PNG, cut short (not ending with its IEND chunk)."""
    d = contract.frame_dir(root, sequence, frame)
    try:
        json.loads((d / "labels.json").read_text())
        problems = []
    except FileNotFoundError:
        return [LABELS_MISSING]
    except (OSError, ValueError):  # ValueError: JSON cut short or not UTF-8
        problems = ["labels.json unreadable"]
    if outputs is not None:
        names = [contract.image_name(c, i) for c in outputs.cameras for i in outputs.illuminations]
        names += [contract.depth_name(c) for c in outputs.cameras if "depth" in outputs.aovs]
        problems += [f"{name} missing or damaged" for name in names if not _whole(d / name)]
    return problems


def _whole(path: Path) -> bool:
    """Whether ``path`` is a file of at least 8 bytes and, if a PNG, ends with ``PNG_END``."""
    try:
        with path.open("rb") as f:
            f.seek(-len(PNG_END), os.SEEK_END)
            return path.suffix != ".png" or f.read() == PNG_END
    except OSError:  # absent, or shorter than 8 bytes (seeking before the start)
        return False


def is_complete(root: Path, sequence: str, frame: int, outputs: Outputs | None = None) -> bool:
    """Whether the frame needs no writing again (``frame_problems``)."""
    return not frame_problems(root, sequence, frame, outputs)
