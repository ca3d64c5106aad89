"""The dataset contract on a small hand-made dataset: COCO files load in pycocotools with the right
counts, ``validate`` passes a good dataset and names what is wrong in a broken one."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from pycocotools.coco import COCO

from transtac_sim.dataset import contract
from transtac_sim.dataset.coco import split_of, write_coco
from transtac_sim.dataset.frame_writer import FrameOutput, is_complete, write_frame
from transtac_sim.dataset.manifest import build_manifest, write_manifest
from transtac_sim.dataset.validate import validate_dataset
from transtac_sim.writer.atomic import write_json

W, H = 40, 30


def _marker(i: int, visible_left: bool) -> dict:
    def view(vis, u):
        return {"uv": [u, 10.0], "uv_centroid": [u + 0.1, 10.0], "visible": vis, "bbox": [u - 2, 8.0, u + 2, 12.0]}

    return {"id": i, "xyz_rest_mm": [0, 0, 20], "xyz_mm": [0, 0, 20],
            "left": view(visible_left, 5.0 + 6 * i), "right": view(True, 4.0 + 6 * i)}


def _dataset(root: Path, sequences: int = 6, frames: int = 2) -> list[tuple[str, int]]:
    samples, done = [], []
    for s in range(sequences):
        seq = contract.sequence_name(s)
        for f in range(frames):
            labels = {"sequence": seq, "frame": f, "time_s": f * 0.1, "indenters": [],
                      "solver": {"converged": True, "iterations": 0, "residual": 0.0, "seconds": 0.0},
                      "markers": [_marker(i, visible_left=(i != 1)) for i in range(4)]}
            imgs = {(c, ill): np.full((H, W, 3), 10 * f, np.uint8) for c in ("left", "right") for ill in ("uv", "white")}
            write_frame(root, FrameOutput(seq, f, labels, imgs))
            samples.append({"sequence": seq, "frame": f, "status": "done"})
            done.append((seq, f))
    scene = {"outputs": {"cameras": ["left", "right"], "illuminations": ["uv", "white"], "aovs": []}}
    write_manifest(root, build_manifest(scene, "x.toml", 0, samples, ["render"], {"render": 1.0}, {}))
    K = [[100.0, 0.0, W / 2], [0.0, 100.0, H / 2], [0.0, 0.0, 1.0]]
    write_json(root / "calibration.json", {"image_size": [W, H], "model": "pinhole", "K_left": K, "dist_left": [0.0] * 5,
                                           "K_right": K, "dist_right": [0.0] * 5,
                                           "R": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                                           "T": [-12.0, 0.0, 0.0]})
    write_coco(root, done, ["left", "right"], (W, H), seed=0)
    return done


def test_coco_loads_with_the_right_counts(tmp_path: Path):
    done = _dataset(tmp_path)
    total_images = total_anns = 0
    for split in ("train", "val", "test"):
        coco = COCO(str(tmp_path / "coco" / f"{split}.json"))
        n_frames = sum(split_of(s, 0) == split for s, _ in done)
        assert len(coco.getImgIds()) == 2 * n_frames
        # 3 of 4 markers visible on the left, 4 on the right
        assert len(coco.getAnnIds()) == 7 * n_frames
        for a in coco.loadAnns(coco.getAnnIds()):
            x, y, w, h = a["bbox"]
            assert w == h == 4.0 and x + 2 == a["keypoints"][0]
        total_images += len(coco.getImgIds())
        total_anns += len(coco.getAnnIds())
    assert total_images == 2 * len(done) and total_anns == 7 * len(done)


def test_split_is_by_sequence_and_deterministic():
    names = [contract.sequence_name(i) for i in range(200)]
    splits = [split_of(n, 3) for n in names]
    assert splits == [split_of(n, 3) for n in names]
    frac = {s: splits.count(s) / len(splits) for s in ("train", "val", "test")}
    assert 0.7 < frac["train"] < 0.9 and frac["val"] > 0.03 and frac["test"] > 0.03


def test_validate_passes_a_good_dataset_and_names_problems(tmp_path: Path):
    _dataset(tmp_path, sequences=2)
    assert validate_dataset(tmp_path) == []
    d = contract.frame_dir(tmp_path, "seq_00001", 1)
    (d / "right_white.png").unlink()
    labels = json.loads((d / "labels.json").read_text())
    labels["markers"][0]["left"]["uv"] = [500.0, 10.0]
    labels["markers"].pop()
    (d / "labels.json").write_text(json.dumps(labels))
    problems = validate_dataset(tmp_path)
    assert any("right_white.png: missing" in p for p in problems)
    assert any("outside 40x30" in p for p in problems)
    assert any("marker ids differ from earlier frames of seq_00001" in p for p in problems)


def test_frame_is_complete_only_once_labels_are_written(tmp_path: Path):
    imgs = {("left", "uv"): np.zeros((H, W, 3), np.uint8)}
    with pytest.raises(ValueError, match="uint8 RGB"):
        write_frame(tmp_path, FrameOutput("s", 0, {}, {("left", "uv"): np.zeros((H, W), np.float32)}))
    assert not is_complete(tmp_path, "s", 0)
    write_frame(tmp_path, FrameOutput("s", 0, {"a": 1}, imgs))
    assert is_complete(tmp_path, "s", 0)
    assert not list(tmp_path.rglob("*.tmp"))
