"""The contact sheet of a dataset: a few frames drawn at random (seeded), every image asked for, with
their labels drawn over them (``contact_sheet.png`` in the dataset root)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.config.scene import Outputs
from transtac_sim.dataset import contract
from transtac_sim.reports.contact_sheet import annotate, save_contact_sheet


def dataset_contact_sheet(root: Path, done: list[tuple[str, int]], outputs: Outputs, *, seed: int,
                          frames: int = 3) -> Path | None:
    if not done or not outputs.illuminations:
        return None
    rng = np.random.default_rng(seed)
    picks = sorted(rng.choice(len(done), size=min(frames, len(done)), replace=False))
    tiles = []
    for i in picks:
        seq, frame = done[i]
        d = contract.frame_dir(root, seq, frame)
        labels = json.loads((d / "labels.json").read_text())
        for cam in outputs.cameras:
            for ill in outputs.illuminations:
                bgr = cv2.imread(str(d / contract.image_name(cam, ill)), cv2.IMREAD_COLOR)
                if bgr is None:  # damaged after generate checked it: said in the caption, not a crash at the end
                    tiles.append((f"{seq}/{frame:06d} {cam} {ill} unreadable", np.zeros((1, 1, 3), np.uint8)))
                    continue
                tile = annotate(bgr[..., ::-1], labels, cam, scale=1) if outputs.labels else bgr[..., ::-1]
                tiles.append((f"{seq}/{frame:06d} {cam} {ill}", tile))
    return save_contact_sheet(tiles, Path(root) / "contact_sheet.png",
                              columns=len(outputs.cameras) * len(outputs.illuminations))
