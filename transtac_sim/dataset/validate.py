"""``transtac-sim validate DIR``: check a dataset folder against the contract of DESIGN.md section 4."""

from __future__ import annotations

import json
from pathlib import Path

import cv2

from transtac_sim.dataset import contract

CALIBRATION_KEYS = {"image_size", "K_left", "dist_left", "K_right", "dist_right", "R", "T", "model"}
LABEL_KEYS = {"sequence", "frame", "time_s", "indenters", "solver", "markers"}
MARKER_KEYS = {"id", "xyz_rest_mm", "xyz_mm"}
VIEW_KEYS = {"uv", "uv_centroid", "visible", "bbox"}


def validate_dataset(root: Path) -> list[str]:
    """Every problem found, as ``<file>: <what>``; an empty list means the dataset is valid."""
    root = Path(root)
    problems: list[str] = []
    try:
        manifest = json.loads((root / "manifest.json").read_text())
        calib = json.loads((root / "calibration.json").read_text())
    except (OSError, json.JSONDecodeError) as e:
        return [f"{root}: cannot read manifest.json / calibration.json ({e})"]
    if manifest.get("format_version") != contract.FORMAT_VERSION:
        problems.append(f"manifest.json: format_version {manifest.get('format_version')!r}, expected {contract.FORMAT_VERSION!r}")
    if missing := CALIBRATION_KEYS - set(calib):
        problems.append(f"calibration.json: missing {sorted(missing)}")
    w, h = calib.get("image_size", (0, 0))
    outputs = manifest["scene"]["outputs"]
    ids_of_sequence: dict[str, set[int]] = {}
    for sample in manifest["samples"]:
        if sample["status"] != "done":
            continue
        seq, frame = sample["sequence"], sample["frame"]
        d = contract.frame_dir(root, seq, frame)
        where = d.relative_to(root)
        try:
            labels = json.loads((d / "labels.json").read_text())
        except (OSError, json.JSONDecodeError) as e:
            problems.append(f"{where}/labels.json: unreadable ({e})")
            continue
        if missing := LABEL_KEYS - set(labels):
            problems.append(f"{where}/labels.json: missing {sorted(missing)}")
            continue
        if (labels["sequence"], labels["frame"]) != (seq, frame):
            problems.append(f"{where}/labels.json: says {labels['sequence']}/{labels['frame']}")
        for cam in outputs["cameras"]:
            for ill in outputs["illuminations"]:
                p = d / contract.image_name(cam, ill)
                img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
                if img is None:
                    problems.append(f"{where}/{p.name}: missing or unreadable")
                elif img.shape[:2] != (h, w):
                    problems.append(f"{where}/{p.name}: {img.shape[1]}x{img.shape[0]}, calibration says {w}x{h}")
            if "depth" in outputs["aovs"] and not (d / contract.depth_name(cam)).is_file():
                problems.append(f"{where}/{contract.depth_name(cam)}: missing")
        ids = [m["id"] for m in labels["markers"]]
        if len(set(ids)) != len(ids):
            problems.append(f"{where}/labels.json: repeated marker ids")
        if ids_of_sequence.setdefault(seq, set(ids)) != set(ids):
            problems.append(f"{where}/labels.json: marker ids differ from earlier frames of {seq}")
        for m in labels["markers"]:
            if missing := (MARKER_KEYS | set(outputs["cameras"])) - set(m):
                problems.append(f"{where}/labels.json: marker {m.get('id')} lacks {sorted(missing)}")
                continue
            for cam in outputs["cameras"]:
                v = m[cam]
                if missing := VIEW_KEYS - set(v):
                    problems.append(f"{where}/labels.json: marker {m['id']} {cam} lacks {sorted(missing)}")
                elif v["visible"]:
                    u, vv = v["uv"]
                    x0, y0, x1, y1 = v["bbox"]
                    if not (-0.5 <= u <= w - 0.5 and -0.5 <= vv <= h - 0.5):
                        problems.append(f"{where}/labels.json: marker {m['id']} visible in {cam} at {v['uv']}, outside {w}x{h}")
                    if not (x0 <= x1 and y0 <= y1 and x0 >= -0.5 and y0 >= -0.5 and x1 <= w - 0.5 and y1 <= h - 0.5):
                        problems.append(f"{where}/labels.json: marker {m['id']} {cam} bbox {v['bbox']} outside the image")
    for split in ("train", "val", "test"):
        if not (root / "coco" / f"{split}.json").is_file():
            problems.append(f"coco/{split}.json: missing")
    return problems
