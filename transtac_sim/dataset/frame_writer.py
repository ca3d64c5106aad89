"""Writing one frame of the dataset: images (8-bit PNG), depth (float32 EXR, mm), then labels.json last.

Every file is written atomically; ``labels.json`` going in last is what marks the frame complete.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

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


def is_complete(root: Path, sequence: str, frame: int) -> bool:
    return (contract.frame_dir(root, sequence, frame) / "labels.json").is_file()
