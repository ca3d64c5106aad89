"""``transtac-sim calibrate`` on chessboards rendered with the simulated TransTac cameras (the default hardware
model's intrinsics, distortion and stereo pose): focal lengths within 0.5 % and the baseline within 1 % of the
true ones, from colour (left) and grey (right) images. A board is rendered exactly: each pixel's ray (through
the lens model) meets the board plane, 3x3 samples per pixel."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from transtac_sim.cli import app

REPO = Path(__file__).resolve().parents[1]
BOARD, SQUARE_MM = (8, 5), 2.5


def _render_board(K, dist, R_cam, T_cam, board_R, board_t, size) -> np.ndarray:
    """8-bit image of the board (pose board -> left camera: board_R, board_t) seen by a camera at
    x_cam = R_cam x_left + T_cam."""
    w, h = size
    s = 3
    ys, xs = np.mgrid[0:h * s, 0:w * s]
    pix = np.column_stack([(xs.ravel() + 0.5) / s - 0.5, (ys.ravel() + 0.5) / s - 0.5]).reshape(-1, 1, 2)
    rays = cv2.undistortPoints(pix, K, dist, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-9))
    d_cam = np.column_stack([rays.reshape(-1, 2), np.ones(len(pix))])
    d = d_cam @ R_cam  # camera -> left frame directions
    c = -R_cam.T @ T_cam  # camera centre, left frame
    n, p0 = board_R[:, 2], board_t
    t = ((p0 - c) @ n) / (d @ n)
    local = ((c + t[:, None] * d) - p0) @ board_R  # board coordinates, mm
    i, j = np.floor(local[:, 0] / SQUARE_MM) + 1, np.floor(local[:, 1] / SQUARE_MM) + 1  # squares -1..cols
    inside = (i >= 0) & (i <= BOARD[0]) & (j >= 0) & (j <= BOARD[1]) & (t > 0)
    value = np.where(inside, np.where((i + j) % 2 == 0, 30.0, 220.0), 235.0)  # white border around the board
    img = value.reshape(h * s, w * s).reshape(h, s, w, s).mean(axis=(1, 3))
    return np.repeat(np.clip(np.rint(img), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)


def test_calibrate_recovers_the_simulated_cameras(tmp_path: Path):
    from transtac_sim.scene_setup import load_setup

    truth = load_setup(REPO / "scenes" / "quickstart.toml").sensor.calibration_json()
    K_l, K_r = np.array(truth["K_left"]), np.array(truth["K_right"])
    d_l, d_r = np.array(truth["dist_left"]), np.array(truth["dist_right"])
    R, T, size = np.array(truth["R"]), np.array(truth["T"]), tuple(truth["image_size"])
    rng = np.random.default_rng(0)
    centre = np.array([(BOARD[0] - 1) * SQUARE_MM / 2, (BOARD[1] - 1) * SQUARE_MM / 2, 0.0])
    for k in range(10):
        rot = Rotation.from_euler("xyz", [rng.uniform(-25, 25), rng.uniform(-25, 25), rng.uniform(-20, 20)], degrees=True)
        board_R = rot.as_matrix()
        board_t = np.array([6.0 + rng.uniform(-4, 4), rng.uniform(-4, 4), rng.uniform(16, 24)]) - board_R @ centre
        for cam, K, d, Rc, Tc in (("left", K_l, d_l, np.eye(3), np.zeros(3)), ("right", K_r, d_r, R, T)):
            (tmp_path / cam).mkdir(exist_ok=True)
            image = _render_board(K, d, Rc, Tc, board_R, board_t, size)
            # the right camera's views saved as single-channel PNGs, as a monochrome camera gives them
            cv2.imwrite(str(tmp_path / cam / f"{k:02d}.png"), image[:, :, 0] if cam == "right" else image)
    out = tmp_path / "calibration.json"
    res = CliRunner().invoke(app, ["calibrate", "--left", str(tmp_path / "left"), "--right", str(tmp_path / "right"),
                                   "--board", f"{BOARD[0]}x{BOARD[1]}", "--square-mm", str(SQUARE_MM), "--out", str(out)])
    assert res.exit_code == 0, res.output
    print(" ".join(res.output.split()))  # pairs used, RMS, baseline and focal lengths (pytest -s)
    got = json.loads(out.read_text())
    for key, K in (("K_left", K_l), ("K_right", K_r)):
        f = np.array(got[key])[[0, 1], [0, 1]]
        assert np.all(np.abs(f / K[[0, 1], [0, 1]] - 1) < 0.005), (key, f, K)
    assert abs(np.linalg.norm(got["T"]) / np.linalg.norm(T) - 1) < 0.01


def test_calibrate_says_when_the_board_is_not_found(tmp_path: Path):
    for cam in ("left", "right"):
        (tmp_path / cam).mkdir()
        for k in range(2):
            cv2.imwrite(str(tmp_path / cam / f"{k}.png"), np.full((48, 64, 3), 128, np.uint8))
    out = tmp_path / "calibration.json"
    res = CliRunner().invoke(app, ["calibrate", "--left", str(tmp_path / "left"), "--right", str(tmp_path / "right"),
                                   "--board", "9x6", "--square-mm", "2", "--out", str(out)])
    text = " ".join(res.output.split())
    assert res.exit_code == 2 and "only 0 of 2 pairs" in text and "--board" in text and not out.exists()


@pytest.mark.parametrize("board, square, message", [("0x0", "2", "at least 2x2"), ("-3x6", "2", "at least 2x2"),
                                                     ("9x6", "0", "--square-mm 0.0")])
def test_calibrate_refuses_a_board_or_square_size_that_cannot_be(tmp_path: Path, board: str, square: str,
                                                                  message: str):
    out = tmp_path / "calibration.json"
    res = CliRunner().invoke(app, ["calibrate", "--left", str(tmp_path), "--right", str(tmp_path), "--board", board,
                                   "--square-mm", square, "--out", str(out)])
    assert res.exit_code == 2 and message in " ".join(res.output.split()) and not out.exists()
