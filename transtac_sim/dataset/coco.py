"""COCO export for detector training: one box and one keypoint (the marker centre ``uv``) per visible
marker in each UV image, with train/val/test splits by sequence (a sequence never straddles splits)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from transtac_sim.dataset import contract
from transtac_sim.writer.atomic import write_json

SPLITS = {"train": 0.8, "val": 0.1, "test": 0.1}
CATEGORY = {"id": 1, "name": "marker", "supercategory": "marker", "keypoints": ["centre"], "skeleton": []}


def split_of(sequence: str, seed: int) -> str:
    """Deterministic split of a sequence: a hash of (seed, name) mapped onto the SPLITS fractions."""
    h = int(hashlib.sha256(f"{seed}:{sequence}".encode()).hexdigest()[:8], 16) / 16**8
    acc = 0.0
    for name, frac in SPLITS.items():
        acc += frac
        if h < acc:
            return name
    return "test"


def coco_for(root: Path, frames: list[tuple[str, int]], cameras: list[str], image_size: tuple[int, int]) -> dict:
    """A COCO dict over the UV images of ``frames`` (sequence, frame) of the dataset at ``root``."""
    images, annotations = [], []
    w, h = image_size
    for seq, frame in frames:
        d = contract.frame_dir(root, seq, frame)
        labels = json.loads((d / "labels.json").read_text())
        for cam in cameras:
            image_id = len(images) + 1
            images.append({"id": image_id, "file_name": str((d / contract.image_name(cam, "uv")).relative_to(root)),
                           "width": w, "height": h, "sequence": seq, "frame": frame, "camera": cam})
            for m in labels["markers"]:
                v = m[cam]
                if not v["visible"]:
                    continue
                x0, y0, x1, y1 = v["bbox"]
                annotations.append({
                    "id": len(annotations) + 1, "image_id": image_id, "category_id": 1,
                    "bbox": [x0, y0, x1 - x0, y1 - y0], "area": (x1 - x0) * (y1 - y0), "iscrowd": 0,
                    "keypoints": [v["uv"][0], v["uv"][1], 2], "num_keypoints": 1, "marker_id": m["id"],
                })
    return {"info": {"description": "transtac_sim markers", "version": contract.FORMAT_VERSION},
            "images": images, "annotations": annotations, "categories": [CATEGORY]}


def write_coco(root: Path, frames: list[tuple[str, int]], cameras: list[str], image_size: tuple[int, int],
               seed: int) -> dict[str, int]:
    """Write ``coco/<split>.json`` for every split; returns the image count per split."""
    counts = {}
    for split in SPLITS:
        chosen = [(s, f) for s, f in frames if split_of(s, seed) == split]
        data = coco_for(root, chosen, cameras, image_size)
        write_json(Path(root) / "coco" / f"{split}.json", data)
        counts[split] = len(data["images"])
    return counts
