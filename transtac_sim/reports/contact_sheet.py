"""Contact sheets: the rendered images of frames in a grid, with the labels drawn over them, so a person
can check labels by eye. Per visible marker: its bbox (green), the geometric centre ``uv`` (red cross),
the intensity centroid ``uv_centroid`` (cyan dot) and its id; invisible markers whose ``uv`` lies in the
image are drawn as a grey ring."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from transtac_sim.writer.atomic import atomic_write


def annotate(rgb: np.ndarray, labels: dict, camera: str, scale: int = 2) -> np.ndarray:
    """``rgb`` (H, W, 3) uint8 with ``camera``'s labels drawn, upscaled by ``scale`` for legibility."""
    img = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    img = np.ascontiguousarray(img[..., ::-1])  # RGB -> BGR for OpenCV drawing

    def px(p):  # pixel-centre coordinates -> upscaled drawing coordinates
        return (int(round((p[0] + 0.5) * scale - 0.5)), int(round((p[1] + 0.5) * scale - 0.5)))

    for m in labels["markers"]:
        v = m[camera]
        u = v["uv"]
        if not v["visible"]:
            if u is not None and 0 <= u[0] < rgb.shape[1] and 0 <= u[1] < rgb.shape[0]:
                cv2.circle(img, px(u), 3 * scale, (128, 128, 128), 1)
            continue
        x0, y0, x1, y1 = v["bbox"]
        cv2.rectangle(img, px((x0, y0)), px((x1, y1)), (0, 200, 0), 1)
        cv2.drawMarker(img, px(u), (0, 0, 255), cv2.MARKER_CROSS, 4 * scale, 1)
        if v.get("uv_centroid") is not None:
            cv2.circle(img, px(v["uv_centroid"]), max(1, scale // 2), (255, 255, 0), -1)
        cv2.putText(img, str(m["id"]), (px((x1, y0))[0] + 2, px((x1, y0))[1]), cv2.FONT_HERSHEY_PLAIN,
                    0.5 * scale, (255, 255, 255), 1, cv2.LINE_AA)
    return img[..., ::-1]


def save_contact_sheet(tiles: list[tuple[str, np.ndarray]], path: Path, columns: int = 2) -> Path:
    """Tiles (caption, RGB uint8) laid out in ``columns``, each with its caption above it."""
    h = max(t.shape[0] for _, t in tiles)
    w = max(t.shape[1] for _, t in tiles)
    rows = (len(tiles) + columns - 1) // columns
    bar = 22
    sheet = np.full((rows * (h + bar), columns * w, 3), 30, np.uint8)
    for i, (caption, tile) in enumerate(tiles):
        r, c = divmod(i, columns)
        y, x = r * (h + bar), c * w
        sheet[y + bar : y + bar + tile.shape[0], x : x + tile.shape[1]] = tile
        cv2.putText(sheet, caption, (x + 6, y + 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (235, 235, 235), 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", sheet[..., ::-1])
    return atomic_write(path, lambda f: f.write(buf.tobytes()))
