"""MarkerNet: a compact single-stage, anchor-free, CenterNet-style marker detector (PyTorch).

Input: a 3-channel image normalised by ``normalise`` (H, W multiples of 8, of 16 with ``context``). A
small U-Net backbone (strides 2, 4, 8, and 16 with ``context``; on the way up each coarser map is reduced by a 1x1 convolution, upsampled and added to
the skip connection of the finer one, so fine detail survives) gives a feature map F at stride 2
(``STRIDE``), and three 1x1 heads read it:
    heatmap  Y (1 channel, sigmoid): a Gaussian bump at each marker centre, trained with the focal loss
             of CenterNet (Zhou et al. 2019);
    offset   O (2 channels): the sub-pixel position of the centre inside its stride-2 cell, in cells;
    size     S (2 channels): the marker's box width and height, px.
A marker at (u, v) px sits in cell (floor(u / 2), floor(v / 2)) and O = (u / 2 - cx, v / 2 - cy); decoding
(``decode``) keeps the local maxima of Y above a score threshold and reads O and S there.
The forward pass also returns F, which the optional correlation term of the loss uses.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as fn

STRIDE = 2
#: the image's bright level is this quantile of its brightest channel
BRIGHT_QUANTILE = 0.999


def normalise(image_bgr: np.ndarray) -> np.ndarray:
    """(3, H, W) float32: RGB in [0, ~1] scaled by the image's bright level (99.9th percentile of the
    brightest channel), so that the UV light level and the exposure do not matter."""
    import cv2

    b, g, r = cv2.split(image_bgr)
    bright = max(bright_level(cv2.max(cv2.max(b, g), r)), 4.0)
    out = np.stack([r, g, b]).astype(np.float32)
    out *= np.float32(1.0 / bright)
    return out


def bright_level(gray_u8: np.ndarray, quantile: float = BRIGHT_QUANTILE) -> float:
    """The ``quantile`` of an 8-bit single-channel image, from its histogram (fast)."""
    import cv2

    hist = cv2.calcHist([np.ascontiguousarray(gray_u8)], [0], None, [256], [0, 256]).ravel()
    return float(np.searchsorted(np.cumsum(hist), quantile * hist.sum()))


def _block(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True))


class MarkerNet(nn.Module):
    def __init__(self, width: int = 16, context: bool = False) -> None:
        super().__init__()
        w = width
        self.width, self.context = width, context
        self.stem = nn.Sequential(_block(3, w, 2), _block(w, w))  # stride 2
        self.down1 = nn.Sequential(_block(w, 2 * w, 2), _block(2 * w, 2 * w))  # stride 4
        self.down2 = nn.Sequential(_block(2 * w, 4 * w, 2), _block(4 * w, 4 * w), _block(4 * w, 4 * w))  # 8
        if context:  # a stride-16 level added back into stride 8: a wider view of the marker pattern
            self.down3 = nn.Sequential(_block(4 * w, 4 * w, 2), _block(4 * w, 4 * w), _block(4 * w, 4 * w))
            self.lateral16 = nn.Conv2d(4 * w, 4 * w, 1)
        self.lateral8 = nn.Conv2d(4 * w, 2 * w, 1)
        self.up1 = _block(2 * w, 2 * w)  # stride 4
        self.lateral4 = nn.Conv2d(2 * w, w, 1)
        self.up0 = _block(w, w)  # stride 2
        self.heatmap = nn.Conv2d(w, 1, 1)
        self.offset = nn.Conv2d(w, 2, 1)
        self.size = nn.Conv2d(w, 2, 1)
        nn.init.constant_(self.heatmap.bias, -4.6)  # start at p = 0.01 (CenterNet)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        s2 = self.stem(x)
        s4 = self.down1(s2)
        s8 = self.down2(s4)
        if self.context:
            s8 = s8 + fn.interpolate(self.lateral16(self.down3(s8)), scale_factor=2.0, mode="nearest")
        u4 = self.up1(fn.interpolate(self.lateral8(s8), scale_factor=2.0, mode="nearest") + s4)
        f = self.up0(fn.interpolate(self.lateral4(u4), scale_factor=2.0, mode="nearest") + s2)
        return self.heatmap(f), self.offset(f), self.size(f), f


def decode(heat_logits: np.ndarray, offset: np.ndarray, size: np.ndarray, score_threshold: float = 0.3,
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Markers from one image's head outputs ((1, h, w), (2, h, w), (2, h, w), numpy): centres (N, 2) px,
    scores (N,), sizes (N, 2) px. A peak is a cell whose score is the maximum of its 3x3 neighbourhood."""
    import cv2

    score = 1.0 / (1.0 + np.exp(-heat_logits[0].astype(np.float32)))
    peaks = (score >= cv2.dilate(score, np.ones((3, 3), np.uint8))) & (score >= score_threshold)
    cy, cx = np.nonzero(peaks)
    uv = np.stack([(cx + offset[0, cy, cx]) * STRIDE, (cy + offset[1, cy, cx]) * STRIDE], axis=1)
    # (cell + offset) * stride is the position in the image whose pixel (0, 0) covers [0, 1) x [0, 1);
    # OpenCV's convention puts that pixel's centre at 0, hence -0.5.
    return uv - 0.5, score[cy, cx], np.stack([size[0, cy, cx], size[1, cy, cx]], axis=1)
