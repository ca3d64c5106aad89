"""Training targets of MarkerNet for one image crop (see ``detection.network`` for the heads).

For a marker at (u, v) px (OpenCV convention) the continuous position is p = (u + 0.5, v + 0.5); its cell is
c = floor(p / STRIDE) and its offset p / STRIDE - c. The heatmap is the maximum over markers of
exp(-|x - c|^2 / (2 sigma^2)) on the cell grid, 1 exactly at each centre cell; offset and size are set at
centre cells only (``mask``).
"""

from __future__ import annotations

import numpy as np

from transtac_sim.perception.detection.network import STRIDE

SIGMA_CELLS = 0.8


def make_targets(uv: np.ndarray, size_px: np.ndarray, shape_hw: tuple[int, int]) -> dict[str, np.ndarray]:
    """Targets for markers ``uv`` (N, 2) with box sizes ``size_px`` (N, 2) on an image of ``shape_hw``:
    heat (1, h, w), offset (2, h, w), size (2, h, w), mask (1, h, w), and ``centres`` (N, 2) int cells
    (x, y) of the markers inside the grid."""
    h, w = shape_hw[0] // STRIDE, shape_hw[1] // STRIDE
    heat = np.zeros((h, w), np.float32)
    offset = np.zeros((2, h, w), np.float32)
    size = np.zeros((2, h, w), np.float32)
    mask = np.zeros((h, w), np.float32)
    p = (np.asarray(uv, np.float64).reshape(-1, 2) + 0.5) / STRIDE
    cells = np.floor(p).astype(int)
    inside = (cells[:, 0] >= 0) & (cells[:, 0] < w) & (cells[:, 1] >= 0) & (cells[:, 1] < h)
    r = int(np.ceil(3 * SIGMA_CELLS))
    gy, gx = np.mgrid[-r:r + 1, -r:r + 1]
    bump = np.exp(-(gx**2 + gy**2) / (2 * SIGMA_CELLS**2)).astype(np.float32)
    for (cx, cy), frac, sz in zip(cells[inside], p[inside] - cells[inside], np.asarray(size_px)[inside], strict=True):
        y0, y1, x0, x1 = max(cy - r, 0), min(cy + r + 1, h), max(cx - r, 0), min(cx + r + 1, w)
        heat[y0:y1, x0:x1] = np.maximum(heat[y0:y1, x0:x1], bump[y0 - cy + r:y1 - cy + r, x0 - cx + r:x1 - cx + r])
        offset[:, cy, cx] = frac
        size[:, cy, cx] = sz
        mask[cy, cx] = 1.0
    return {"heat": heat[None], "offset": offset, "size": size, "mask": mask[None], "centres": cells[inside]}
