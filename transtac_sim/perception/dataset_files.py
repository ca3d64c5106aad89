"""Reading a generated dataset's files (the dataset contract: ``sequences/<seq>/<frame:06d>/`` with
``<camera>_uv.png``, ``<camera>_white.png`` and ``labels.json``) for training and evaluation. Only the
file format is used: this module does not import the simulator."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from transtac_sim.perception.errors import PerceptionInputError

CAMERAS = ("left", "right")


@dataclass(frozen=True)
class MarkerTruth:
    """The visible markers of one image: ids, centres (``uv_centroid``, px) and boxes (x0, y0, x1, y1)."""

    ids: np.ndarray  # (N,)
    uv: np.ndarray  # (N, 2)
    bbox: np.ndarray  # (N, 4)


@dataclass(frozen=True)
class LabelledImage:
    dataset: Path
    sequence: str
    frame: int
    camera: str
    uv_path: Path
    white_path: Path | None
    truth: MarkerTruth
    labels: dict  # the whole labels.json


def truth_of(labels: dict, camera: str) -> MarkerTruth:
    ids, uv, bbox = [], [], []
    for m in labels["markers"]:
        view = m.get(camera)
        if not view or not view["visible"]:
            continue
        ids.append(m["id"])
        uv.append(view["uv_centroid"] if view.get("uv_centroid") is not None else view["uv"])
        bbox.append(view["bbox"])
    return MarkerTruth(np.array(ids, dtype=np.int64), np.array(uv, dtype=np.float64).reshape(-1, 2),
                       np.array(bbox, dtype=np.float64).reshape(-1, 4))


def sequences(dataset: Path) -> list[str]:
    root = Path(dataset) / "sequences"
    if not root.is_dir():
        raise PerceptionInputError(dataset, "not a dataset folder (no sequences/)",
                                   "pass a folder written by `transtac-sim generate`")
    return sorted(p.name for p in root.iterdir() if p.is_dir())


def pick_sequence(dataset: Path, sequence: str | None) -> str:
    """``sequence`` if the dataset has it, else (None) its first sequence; PerceptionInputError otherwise."""
    seqs = sequences(dataset)
    seq = sequence or (seqs[0] if seqs else None)
    if seq not in seqs:
        raise PerceptionInputError(dataset, f"no sequence {seq!r} (has: {', '.join(seqs[:8]) or 'none'})",
                                   "pick one with --sequence")
    return seq


def complete_frames(dataset: Path, sequence: str) -> list[Path]:
    """A sequence's finished frame folders (those with ``labels.json``, which the generator writes last), in frame
    order. (The generator's own resume test, ``dataset/frame_writer.py``, also checks the images are whole; readers
    here name a missing or unreadable image when they open it.)"""
    root = Path(dataset) / "sequences" / sequence
    return [f for f in sorted(root.iterdir()) if f.is_dir() and (f / "labels.json").is_file()]


def labelled_images(dataset: Path, only: set[str] | None = None, cameras=CAMERAS) -> Iterator[LabelledImage]:
    """Every complete frame's UV image per camera, with its truth, in sequence and frame order."""
    dataset = Path(dataset)
    for seq in sequences(dataset):
        if only is not None and seq not in only:
            continue
        for fdir in complete_frames(dataset, seq):
            labels = json.loads((fdir / "labels.json").read_text())
            for cam in cameras:
                uv_path = fdir / f"{cam}_uv.png"
                if not uv_path.is_file():
                    continue
                white = fdir / f"{cam}_white.png"
                yield LabelledImage(dataset, seq, int(fdir.name), cam, uv_path, white if white.is_file() else None,
                                    truth_of(labels, cam), labels)
