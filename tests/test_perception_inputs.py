"""Bad input to the perception commands: one clear line naming the file and what to do, exit status 2, and
no output file."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from synthetic_markers import draw_markers, grid_markers
from typer.testing import CliRunner

from transtac_sim.cli import app
from transtac_sim.perception.detection.model_file import load_model
from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.perception.images import find_images, read_color_image

runner = CliRunner()


def _detect(args: list[str], out: Path):
    res = runner.invoke(app, ["detect", *args, "--out", str(out)])
    return res, " ".join(res.output.split())


@pytest.fixture
def images(tmp_path: Path) -> Path:
    d = tmp_path / "frames"
    d.mkdir()
    for i in range(2):
        cv2.imwrite(str(d / f"{i:03d}.png"), draw_markers(grid_markers()))
    return d


def test_missing_empty_unreadable_and_grayscale_images_are_named(tmp_path: Path):
    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "text.png").write_text("not an image")
    cv2.imwrite(str(tmp_path / "gray.png"), np.zeros((20, 20), np.uint8))
    for name, words in (("nope.png", "not found"), ("empty.png", "empty"), ("text.png", "not a readable image"),
                        ("gray.png", "grayscale")):
        with pytest.raises(PerceptionInputError) as e:
            read_color_image(tmp_path / name)
        assert str(tmp_path / name) in str(e.value) and words in str(e.value)
    (tmp_path / "no_images").mkdir()
    with pytest.raises(PerceptionInputError, match="no images"):
        find_images(tmp_path / "no_images")


def test_a_bad_image_in_a_folder_stops_detect_before_anything_is_written(images: Path, tmp_path: Path):
    cv2.imwrite(str(images / "zz_gray.png"), np.zeros((96, 128), np.uint8))
    out = tmp_path / "det.json"
    res, text = _detect([str(images), "--method", "blob"], out)
    assert res.exit_code == 2 and "zz_gray.png" in text and "grayscale" in text
    assert not out.exists()


def test_image_size_the_model_was_not_trained_for(images: Path, tmp_path: Path):
    out = tmp_path / "det.json"
    res, text = _detect([str(images), "--method", "learned"], out)  # 128x96 frames, the shipped model: 640x480
    assert res.exit_code == 2 and "000.png" in text and "128x96" in text and "640x480" in text
    assert not out.exists()


def test_a_file_that_is_not_a_detector_model(tmp_path: Path, images: Path):
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"\x00" * 100)
    other = tmp_path / "other.pt"
    torch.save({"weights": torch.zeros(3)}, other)
    for path in (junk, other, tmp_path / "missing.pt"):
        with pytest.raises(PerceptionInputError) as e:
            load_model(path)
        assert str(path) in str(e.value) and "train-detector" in str(e.value)
    out = tmp_path / "det.json"
    res, text = _detect([str(images), "--model", str(other)], out)
    assert res.exit_code == 2 and "not a detector model" in text and not out.exists()


def test_detect_on_a_folder_writes_the_contract_file(images: Path, tmp_path: Path):
    import json

    out = tmp_path / "det.json"
    res, _ = _detect([str(images), "--method", "blob", "--preview", str(tmp_path / "p.png")], out)
    assert res.exit_code == 0, res.output
    assert cv2.imread(str(tmp_path / "p.png")).shape == (2 * 96, 2 * 128, 3)  # the first image, enlarged 2x
    data = json.loads(out.read_text())
    assert data["method"] == "blob" and data["model"] is None
    assert [Path(e["path"]).name for e in data["images"]] == ["000.png", "001.png"]
    assert len(data["images"][0]["markers"]) == len(grid_markers())
    assert set(data["images"][0]["markers"][0]) == {"uv", "score"}


def test_detect_and_track_on_a_dataset_folder(tmp_path: Path):
    import json

    from synthetic_markers import write_tiny_dataset

    ds = write_tiny_dataset(tmp_path / "ds", sequences=2, frames=3)
    res = runner.invoke(app, ["detect", str(ds), "--method", "blob", "--out", str(tmp_path / "d.json")])
    assert res.exit_code == 0, res.output
    paths = [e["path"] for e in json.loads((tmp_path / "d.json").read_text())["images"]]
    assert len(paths) == 12 and paths[0] == "sequences/seq_00000/000000/left_uv.png"
    res = runner.invoke(app, ["track", str(ds), "--detector", "blob", "--sequence", "seq_00001", "--camera", "right",
                              "--out", str(tmp_path / "t.json")])
    assert res.exit_code == 0, res.output
    frames = json.loads((tmp_path / "t.json").read_text())["frames"]
    assert [f["path"] for f in frames] == [f"sequences/seq_00001/{k:06d}/right_uv.png" for k in range(3)]
    last = frames[-1]["markers"]
    assert all(m["track_id"] >= 0 for m in last)
    assert np.allclose([m["displacement_px"] for m in last], [1.4, 0.8], atol=0.05)  # 0.7, 0.4 px per frame
    res = runner.invoke(app, ["track", str(ds), "--sequence", "nope", "--out", str(tmp_path / "t2.json")])
    assert res.exit_code == 2 and "no sequence 'nope'" in " ".join(res.output.split())


def test_detect_preview_of_a_first_image_without_markers_draws_none(tmp_path: Path):
    """The preview shows the first image with its own markers, also when it has none (a blank frame)."""
    d = tmp_path / "frames"
    d.mkdir()
    cv2.imwrite(str(d / "000.png"), np.zeros((96, 128, 3), np.uint8))
    cv2.imwrite(str(d / "001.png"), draw_markers(grid_markers()))
    res, _ = _detect([str(d), "--method", "blob", "--preview", str(tmp_path / "p.png")], tmp_path / "det.json")
    assert res.exit_code == 0, res.output
    assert cv2.imread(str(tmp_path / "p.png")).max() == 0  # no circle drawn


def test_dataset_commands_take_the_complete_frames_and_name_a_missing_view(tmp_path: Path):
    """labels.json is written last: a frame folder without it is unfinished and left out (detect, track,
    reconstruct). A complete frame without one camera's image is named, not skipped or paired with another frame's
    image."""
    import json

    from synthetic_markers import write_tiny_dataset

    ds = write_tiny_dataset(tmp_path / "ds", sequences=1, frames=4)
    (ds / "sequences/seq_00000/000003/labels.json").unlink()
    res = runner.invoke(app, ["detect", str(ds), "--method", "blob", "--out", str(tmp_path / "d.json")])
    assert res.exit_code == 0, res.output
    assert len(json.loads((tmp_path / "d.json").read_text())["images"]) == 6  # 3 complete frames, 2 cameras
    res = runner.invoke(app, ["track", str(ds), "--detector", "blob", "--out", str(tmp_path / "t.json")])
    assert res.exit_code == 0, res.output
    frames = json.loads((tmp_path / "t.json").read_text())["frames"]
    assert [f["path"] for f in frames] == [f"sequences/seq_00000/{k:06d}/left_uv.png" for k in range(3)]
    k = [[100.0, 0.0, 63.5], [0.0, 100.0, 47.5], [0.0, 0.0, 1.0]]
    (ds / "calibration.json").write_text(json.dumps({
        "image_size": [128, 96], "model": "pinhole", "K_left": k, "dist_left": [0.0] * 5, "K_right": k,
        "dist_right": [0.0] * 5, "R": np.eye(3).tolist(), "T": [-12.0, 0.0, 0.0]}))
    (ds / "sequences/seq_00000/000001/right_uv.png").unlink()
    res = runner.invoke(app, ["reconstruct", "--dataset", str(ds), "--detector", "blob", "--out", str(tmp_path / "r")])
    text = " ".join(res.output.split())
    assert res.exit_code == 2 and "000001" in text and "right_uv.png" in text and not (tmp_path / "r").exists()
    res = runner.invoke(app, ["detect", str(ds), "--method", "blob", "--out", str(tmp_path / "d2.json")])
    text = " ".join(res.output.split())
    assert res.exit_code == 2 and "000001: complete frame without right_uv.png" in text
    assert not (tmp_path / "d2.json").exists()


def test_device_camera_and_output_mistakes_are_named(images: Path, tmp_path: Path):
    """An unknown --device, a GPU asked for where torch has none, a folder as --out and an unknown --camera each
    end with one line saying what to change, and nothing written."""
    res, text = _detect([str(images), "--device", "tpu"], tmp_path / "d.json")
    assert res.exit_code == 2 and "auto, cpu or cuda" in text and not (tmp_path / "d.json").exists()
    if not torch.cuda.is_available():
        res, text = _detect([str(images), "--device", "cuda"], tmp_path / "d.json")
        assert res.exit_code == 2 and "no CUDA GPU" in text and not (tmp_path / "d.json").exists()
    res, text = _detect([str(images), "--method", "blob"], images)
    assert res.exit_code == 2 and "is a folder" in text
    assert sorted(p.name for p in images.iterdir()) == ["000.png", "001.png"]
    res = runner.invoke(app, ["track", str(images), "--camera", "middle", "--detector", "blob",
                              "--out", str(tmp_path / "t.json")])
    assert res.exit_code == 2 and "unknown camera 'middle'" in " ".join(res.output.split())
    cv2.imwrite(str(images / "002.png"), draw_markers(grid_markers((48, 64)), (48, 64)))
    res = runner.invoke(app, ["track", str(images), "--detector", "blob", "--out", str(tmp_path / "t.json")])
    assert res.exit_code == 2 and "image is 64x48 px, the first frame 128x96" in " ".join(res.output.split())
    assert not (tmp_path / "t.json").exists()
