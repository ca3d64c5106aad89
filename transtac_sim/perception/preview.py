"""Pictures for people: an image with its detected markers circled."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from transtac_sim.writer.atomic import atomic_write


def detection_preview(image_bgr: np.ndarray, uv: np.ndarray, path: Path, scale: int = 2) -> Path:
    """PNG of ``image_bgr`` brightened to its 99.9th percentile, enlarged ``scale`` times, with a circle at
    each ``uv`` (px)."""
    img = image_bgr.astype(np.float32)
    img = np.clip(img * (230.0 / max(float(np.percentile(img, 99.9)), 1.0)), 0, 255).astype(np.uint8)
    img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    for u, v in np.asarray(uv).reshape(-1, 2):
        c = (int(round((u + 0.5) * scale - 0.5)), int(round((v + 0.5) * scale - 0.5)))
        cv2.circle(img, c, 6 * scale, (0, 0, 255), 1, cv2.LINE_AA)
    ok, buf = cv2.imencode(".png", img)
    return atomic_write(Path(path), lambda f: f.write(buf.tobytes()))
