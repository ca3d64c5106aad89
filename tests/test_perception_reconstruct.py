"""``transtac-sim reconstruct`` end to end on a synthetic pinhole stereo pair with exactly known 3D markers,
and its bad inputs (one line naming the file, nothing written)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from synthetic_markers import draw_markers
from typer.testing import CliRunner

from transtac_sim.cli import app

runner = CliRunner()
SHAPE = (240, 320)
F_PX, BASELINE_MM, Z_MM = 200.0, 12.0, 20.0


def _calibration() -> dict:
    k = [[F_PX, 0.0, 159.5], [0.0, F_PX, 119.5], [0.0, 0.0, 1.0]]
    return {"image_size": [SHAPE[1], SHAPE[0]], "model": "pinhole", "K_left": k, "dist_left": [0.0] * 5,
            "K_right": k, "dist_right": [0.0] * 5, "R": np.eye(3).tolist(), "T": [-BASELINE_MM, 0.0, 0.0]}


def _scene(tmp_path: Path, frames: int = 2) -> tuple[Path, np.ndarray]:
    """calibration.json, left/ and right/ folders of markers on a plane z = 20 mm, moving 0.3 mm per frame."""
    rng = np.random.default_rng(3)
    gx, gy = np.meshgrid(np.arange(2.0, 10.1, 2.0), np.arange(-8.0, 8.1, 2.0))
    base = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, Z_MM)]) + rng.uniform(-0.3, 0.3, (gx.size, 3)) * [1, 1, 0]
    (tmp_path / "calibration.json").write_text(json.dumps(_calibration()))
    truth = []
    for f in range(frames):
        xyz = base + [0.3 * f, 0.0, 0.0]
        for cam, shift in (("left", 0.0), ("right", -BASELINE_MM)):
            uv = np.column_stack([F_PX * (xyz[:, 0] + shift) / xyz[:, 2] + 159.5, F_PX * xyz[:, 1] / xyz[:, 2] + 119.5])
            (tmp_path / cam).mkdir(exist_ok=True)
            cv2.imwrite(str(tmp_path / cam / f"{f:03d}.png"), draw_markers(uv, SHAPE, radius_px=3.0))
        truth.append(xyz)
    return tmp_path, np.array(truth)


def _run(root: Path, out: Path, *extra: str):
    res = runner.invoke(app, ["reconstruct", "--calibration", str(root / "calibration.json"), "--left", str(root / "left"),
                              "--right", str(root / "right"), "--detector", "blob", "--out", str(out), *extra])
    return res, " ".join(res.output.split())


@pytest.mark.parametrize("matcher", ["delaunay", "hungarian"])
def test_reconstruct_recovers_the_markers_in_3d(tmp_path: Path, matcher: str):
    root, truth = _scene(tmp_path)
    res, text = _run(root, tmp_path / "out", "--matcher", matcher)
    assert res.exit_code == 0, text
    for f in range(2):
        rec = json.loads((tmp_path / "out" / "frames" / f"{f:06d}.json").read_text())
        assert set(rec) >= {"frame", "source", "left", "right", "matches", "seconds"}
        xyz = np.array([m["xyz_mm"] for m in rec["matches"]])
        assert len(xyz) == len(truth[f])
        err = np.linalg.norm(xyz[:, None] - truth[f][None], axis=2).min(1)
        assert err.max() < 0.05, err.max()
        ids = [m["track_id"] for m in rec["matches"]]
        assert min(ids) >= 0 and len(set(ids)) == len(ids)
    first = {m["track_id"]: m["xyz_mm"] for m in json.loads((tmp_path / "out/frames/000000.json").read_text())["matches"]}
    second = json.loads((tmp_path / "out/frames/000001.json").read_text())["matches"]
    moved = [np.subtract(m["xyz_mm"], first[m["track_id"]]) for m in second if m["track_id"] in first]
    assert np.allclose(moved, [0.3, 0.0, 0.0], atol=0.05)  # the same track is the same marker
    assert (tmp_path / "out" / "preview.png").is_file() and json.loads((tmp_path / "out/summary.json").read_text())["frames"] == 2


def test_frame_with_too_few_markers_is_written_with_its_reason(tmp_path: Path):
    root, _ = _scene(tmp_path, frames=1)
    cv2.imwrite(str(root / "right" / "000.png"), np.zeros((*SHAPE, 3), np.uint8))
    res, text = _run(root, tmp_path / "out")
    assert res.exit_code == 0, text
    rec = json.loads((tmp_path / "out/frames/000000.json").read_text())
    assert rec["matches"] == [] and "too few markers" in rec["reason"]


def test_bad_inputs_name_the_file_and_write_nothing(tmp_path: Path):
    root, _ = _scene(tmp_path, frames=2)
    (root / "right" / "001.png").unlink()
    res, text = _run(root, tmp_path / "out")
    assert res.exit_code == 2 and "2 left frames but 1 right frames" in text and not (tmp_path / "out").exists()
    (root / "video.mp4").write_bytes(b"not a video")
    res = runner.invoke(app, ["reconstruct", "--calibration", str(root / "calibration.json"), "--left", str(root / "video.mp4"),
                              "--right", str(root / "video.mp4"), "--out", str(tmp_path / "out")])
    assert res.exit_code == 2 and "video cannot be opened" in " ".join(res.output.split()) and not (tmp_path / "out").exists()
    res = runner.invoke(app, ["reconstruct", "--dataset", str(root), "--calibration", str(root / "calibration.json"),
                              "--out", str(tmp_path / "out")])
    assert res.exit_code == 2 and "--dataset alone" in " ".join(res.output.split()) and not (tmp_path / "out").exists()
    calib = _calibration()
    del calib["T"]
    (root / "calibration.json").write_text(json.dumps(calib))
    res, text = _run(root, tmp_path / "out")
    assert res.exit_code == 2 and "calibration.json" in text and "T" in text and not (tmp_path / "out").exists()
    calib = _calibration() | {"image_size": [640, 480]}
    (root / "calibration.json").write_text(json.dumps(calib))
    cv2.imwrite(str(root / "right" / "001.png"), np.zeros((*SHAPE, 3), np.uint8))
    res, text = _run(root, tmp_path / "out")
    assert res.exit_code == 2 and "320" in text and "640" in text and not (tmp_path / "out").exists()


def test_dense_needs_the_white_light_images(tmp_path: Path):
    root, _ = _scene(tmp_path, frames=1)
    res, text = _run(root, tmp_path / "out", "--dense", "sgbm")
    assert res.exit_code == 2 and "--left-white" in text and not (tmp_path / "out").exists()


def test_learned_stereo_and_anchor_options_refuse_what_is_missing(tmp_path: Path):
    root, _ = _scene(tmp_path, frames=1)
    white = ["--left-white", str(root / "left"), "--right-white", str(root / "right")]
    res, text = _run(root, tmp_path / "out", "--dense", "onnx", *white)
    assert res.exit_code == 2 and "--stereo-model" in text and not (tmp_path / "out").exists()
    res, text = _run(root, tmp_path / "out", "--dense", "onnx", "--stereo-model", str(root / "none.onnx"), *white)
    assert res.exit_code == 2 and "none.onnx" in text and "never downloaded" in text and not (tmp_path / "out").exists()
    res, text = _run(root, tmp_path / "out", "--dense", "sgbm", "--anchors", "distance-aware", *white)
    assert res.exit_code == 2 and "gel_thickness_mm" in text and not (tmp_path / "out").exists()


def test_preview_video_has_a_frame_per_stereo_frame(tmp_path: Path):
    root, _ = _scene(tmp_path, frames=3)
    res, text = _run(root, tmp_path / "out", "--preview", "video")
    assert res.exit_code == 0, text
    cap = cv2.VideoCapture(str(tmp_path / "out" / "preview.mp4"))
    count, shape = 0, None
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        count, shape = count + 1, frame.shape
    assert count == 3 and shape[1] == 3 * SHAPE[1]  # left, right and the depth panel
    assert not (tmp_path / "out" / "preview.png").exists()


def test_output_folder_of_something_else_is_refused_and_a_rerun_replaces_its_own_files(tmp_path: Path):
    """--out must be new, empty or an earlier reconstruct output (an interrupted one too): a folder of other files
    is refused with nothing changed; a re-run with fewer frames replaces the earlier run's files, none of them left
    stale, and leaves no staging folder."""
    root, _ = _scene(tmp_path, frames=2)
    for name, text in (("summary.json", '{"kind": "transtac-sim simulate"}'), ("notes.txt", "mine")):
        other = tmp_path / "other" / name
        other.parent.mkdir(exist_ok=True)
        other.write_text(text)
        res, message = _run(root, other.parent)
        assert res.exit_code == 2 and "not an earlier reconstruct output" in message
        assert other.read_text() == text
        other.unlink()
    out = tmp_path / "out"
    (out / "frames").mkdir(parents=True)
    (out / "frames" / "000007.json").write_text("{}")  # a first run interrupted: no summary yet
    assert _run(root, out)[0].exit_code == 0
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["000000.json", "000001.json"]
    for cam in ("left", "right"):
        (root / cam / "001.png").unlink()
    res, _ = _run(root, out)
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (out / "frames").iterdir()) == ["000000.json"]
    assert json.loads((out / "summary.json").read_text())["frames"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration.json", "left", "other", "out", "right"]
    assert sorted(p.name for p in out.iterdir()) == ["frames", "preview.png", "summary.json"]
