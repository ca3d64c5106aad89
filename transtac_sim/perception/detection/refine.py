"""Sub-pixel marker centres by the intensity-weighted centroid of a window around a first estimate.

For a window W of half-size r (one for all markers) around the pixel nearest (u0, v0) on a single-channel
image I, with b the window's background (the lower median of its border ring: the k-th smallest,
k = (n - 1) // 2, of its n values):
    u = sum_W (I - b)+ * x / sum_W (I - b)+,  v likewise,
which is what a marker's ``uv_centroid`` label is (the intensity centroid of its image under UV light).
"""

from __future__ import annotations

import numpy as np


def intensity_centroids(gray: np.ndarray, uv: np.ndarray, half_px: int = 5) -> np.ndarray:
    """Refined (N, 2) centres, all windows at once. A window with no signal above its background keeps the
    first estimate."""
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    if len(uv) == 0:
        return uv.copy()
    r = int(half_px)
    padded = np.pad(gray.astype(np.float32), r)
    centre = np.rint(uv).astype(int)
    centre[:, 0] = np.clip(centre[:, 0], 0, gray.shape[1] - 1)
    centre[:, 1] = np.clip(centre[:, 1], 0, gray.shape[0] - 1)
    d = np.arange(-r, r + 1)
    ys = centre[:, 1, None, None] + d[None, :, None]  # (N, 2r+1, 1) in image rows
    xs = centre[:, 0, None, None] + d[None, None, :]
    win = padded[ys + r, xs + r]  # (N, 2r+1, 2r+1)
    ring = np.concatenate([win[:, 0], win[:, -1], win[:, 1:-1, 0], win[:, 1:-1, -1]], axis=1)
    k = (ring.shape[1] - 1) // 2
    wgt = np.clip(win - np.partition(ring, k, axis=1)[:, k][:, None, None], 0.0, None)
    total = wgt.sum(axis=(1, 2))
    ok = total > 0
    u = (wgt * xs).sum(axis=(1, 2)) / np.where(ok, total, 1.0)
    v = (wgt * ys).sum(axis=(1, 2)) / np.where(ok, total, 1.0)
    return np.where(ok[:, None], np.stack([u, v], axis=1), uv)
