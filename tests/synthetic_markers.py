"""Synthetic marker images with exactly known centres, and a tiny dataset folder in the contract's layout,
for the perception tests (no rendering: discs drawn with 8x supersampling)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np


def draw_markers(uv: np.ndarray, shape_hw=(96, 128), radius_px: float = 3.4, level: float = 40.0,
                 background: float = 0.0, supersample: int = 8) -> np.ndarray:
    """8-bit BGR image of green discs centred at ``uv`` (OpenCV convention). The intensity centroid of each
    disc is its centre."""
    h, w = shape_hw
    s = supersample
    ys, xs = (np.mgrid[0:h * s, 0:w * s] + 0.5) / s - 0.5  # sub-sample centres in pixel coordinates
    img = np.zeros((h * s, w * s), np.float32)
    for u, v in uv:
        img[(xs - u) ** 2 + (ys - v) ** 2 <= radius_px**2] = level
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    out = np.zeros((h, w, 3), np.float32)
    out[:, :, 1] = img + background
    out[:, :, 0] = out[:, :, 2] = background
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def grid_markers(shape_hw=(96, 128), spacing_px: float = 16.0, margin_px: float = 10.0,
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """Marker centres on a jittered grid, with sub-pixel positions."""
    rng = rng or np.random.default_rng(0)
    h, w = shape_hw
    gx, gy = np.meshgrid(np.arange(margin_px, w - margin_px, spacing_px), np.arange(margin_px, h - margin_px, spacing_px))
    uv = np.stack([gx.ravel(), gy.ravel()], 1)
    return uv + rng.uniform(-3.0, 3.0, uv.shape)


def write_tiny_dataset(root: Path, sequences: int = 3, frames: int = 2, shape_hw=(96, 128), seed: int = 0) -> Path:
    """``root/sequences/seq_NNNNN/NNNNNN/{left,right}_uv.png`` and ``labels.json`` (the keys the perception
    package reads), markers on a jittered grid that moves a little from frame to frame."""
    rng = np.random.default_rng(seed)
    for s in range(sequences):
        base = grid_markers(shape_hw, rng=rng)
        for f in range(frames):
            d = root / "sequences" / f"seq_{s:05d}" / f"{f:06d}"
            d.mkdir(parents=True, exist_ok=True)
            markers = [{"id": i} for i in range(len(base))]
            for cam, shift in (("left", 0.0), ("right", -2.0)):
                uv = base + [shift + 0.7 * f, 0.4 * f]
                cv2.imwrite(str(d / f"{cam}_uv.png"), draw_markers(uv, shape_hw, level=float(rng.uniform(25, 60))))
                for m, (u, v) in zip(markers, uv, strict=True):
                    m[cam] = {"uv": [u, v], "uv_centroid": [u, v], "visible": True, "bbox": [u - 3.5, v - 3.5, u + 3.5, v + 3.5]}
            (d / "labels.json").write_text(json.dumps({"sequence": f"seq_{s:05d}", "frame": f, "markers": markers}))
    return root
