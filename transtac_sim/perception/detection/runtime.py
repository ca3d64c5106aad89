"""Running the learned detector on images: pre-processing (``network.normalise``), the network, decoding
(``network.decode``) and, by default, the intensity-centroid refinement of each centre in a window the
size head gives (``refine``).

Two backends compute the same thing: ``onnx`` (onnxruntime, numpy pre- and post-processing; the faster
one on a CPU) and ``torch`` (every step on the device as tensors, only the peaks copied back: the one for
a GPU). ``backend="auto"`` picks torch on a CUDA device and onnx on the CPU.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as fn

from transtac_sim.perception.detection import Detections
from transtac_sim.perception.detection.blob import marker_response
from transtac_sim.perception.detection.model_file import DEFAULT_MODEL, load_model
from transtac_sim.perception.detection.network import BRIGHT_QUANTILE, STRIDE, decode, normalise
from transtac_sim.perception.detection.refine import intensity_centroids
from transtac_sim.perception.errors import PerceptionInputError

#: peaks below this score are dropped: the F1-best threshold on the training sets' validation split
#: (scripts/choose_score_threshold.py)
DEFAULT_SCORE_THRESHOLD = 0.4


class LearnedDetector:
    def __init__(self, model_path: Path | None = None, *, device: str = "auto", backend: str = "auto",
                 score_threshold: float = DEFAULT_SCORE_THRESHOLD, refine: bool = True) -> None:
        if not (device in ("auto", "cpu", "cuda") or device.startswith("cuda:")):
            raise ValueError(f"--device {device!r}: auto, cpu or cuda")
        if device.startswith("cuda") and not torch.cuda.is_available():
            raise ValueError(f"--device {device}: torch finds no CUDA GPU here; use --device cpu (or auto)")
        self.model_path = Path(model_path) if model_path else DEFAULT_MODEL
        self.net, self.meta = load_model(self.model_path)
        self.device = ("cuda" if torch.cuda.is_available() else "cpu") if device == "auto" else device
        self.backend = ("torch" if self.device.startswith("cuda") else "onnx") if backend == "auto" else backend
        self.score_threshold, self.refine = score_threshold, refine
        if self.backend == "onnx":
            import onnxruntime as ort

            onnx_path = self.model_path.with_suffix(".onnx")
            if not onnx_path.is_file():
                raise PerceptionInputError(onnx_path, "the model's ONNX export is missing",
                                           "re-save the model with `transtac-sim train-detector` (it writes the .onnx "
                                           "beside the .pt), or run the torch model on a GPU (--device cuda)")
            self.session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
        else:
            self.net = self.net.to(self.device)

    def check_size(self, image: np.ndarray, name: str) -> None:
        h, w = image.shape[:2]
        if (w, h) not in self.meta["image_sizes"]:
            sizes = ", ".join(f"{a}x{b}" for a, b in self.meta["image_sizes"])
            raise PerceptionInputError(name, f"image is {w}x{h}, the model was trained on {sizes}",
                                       "resize the images or train a model on this size (train-detector)")

    def detect(self, images: list[np.ndarray]) -> list[Detections]:
        """Markers in each 8-bit BGR image (all of one size, one the model was trained on), as one batch."""
        return self._detect_onnx(images) if self.backend == "onnx" else self._detect_torch(images)

    def _detect_onnx(self, images: list[np.ndarray]) -> list[Detections]:
        t0 = time.perf_counter()
        batch = np.stack([normalise(im) for im in images])
        t1 = time.perf_counter()
        heat, offset, size = self.session.run(None, {"image": batch})
        t2 = time.perf_counter()
        results = []
        for b, im in enumerate(images):
            uv, score, sz = decode(heat[b], offset[b], size[b], self.score_threshold)
            if self.refine and len(uv):
                uv = intensity_centroids(marker_response(im), uv, refine_half_px(sz))
            results.append(Detections(uv, score, sz))
        t3 = time.perf_counter()
        seconds = {"preprocess": t1 - t0, "network": t2 - t1, "decode": t3 - t2}
        return [Detections(r.uv, r.score, r.size, seconds, self.score_threshold) for r in results]

    @torch.no_grad()
    def _detect_torch(self, images: list[np.ndarray]) -> list[Detections]:
        sync = torch.cuda.synchronize if self.device.startswith("cuda") else (lambda: None)
        t0 = time.perf_counter()
        raw = torch.from_numpy(np.stack(images)).to(self.device)  # (B, H, W, 3) uint8 BGR
        x = raw.permute(0, 3, 1, 2).float()
        bright = _bright_levels(raw.amax(dim=3)).clamp(min=4.0)  # as network.bright_level, per image
        inp = x.flip(1) / bright[:, None, None, None]
        sync()
        t1 = time.perf_counter()
        heat, offset, size, _ = self.net(inp)
        sync()
        t2 = time.perf_counter()
        score = torch.sigmoid(heat.float())
        peaks = (score >= fn.max_pool2d(score, 3, 1, 1)) & (score >= self.score_threshold)
        b, _, cy, cx = peaks.nonzero(as_tuple=True)
        uv = torch.stack([(cx + offset[b, 0, cy, cx]) * STRIDE, (cy + offset[b, 1, cy, cx]) * STRIDE], 1).double() - 0.5
        sz = torch.stack([size[b, 0, cy, cx], size[b, 1, cy, cx]], 1).float()
        conf = score[b, 0, cy, cx]
        if self.refine and len(uv):
            response = (x[:, 1] - 0.5 * (x[:, 0] + x[:, 2])).clamp(min=0.0)
            uv = _centroids_torch(response, b, uv, refine_half_px(sz.cpu().numpy()))
        counts = torch.bincount(b, minlength=len(images)).tolist()
        uv, conf, sz = (t.cpu().numpy().astype(np.float64) for t in (uv, conf, sz))
        t3 = time.perf_counter()
        seconds = {"preprocess": t1 - t0, "network": t2 - t1, "decode": t3 - t2}
        ends = np.cumsum([0, *counts])
        return [Detections(uv[a:e], conf[a:e], sz[a:e], seconds, self.score_threshold)
                for a, e in zip(ends[:-1], ends[1:], strict=True)]


def _bright_levels(gray_u8: torch.Tensor) -> torch.Tensor:
    """Per image (B, H, W uint8): the BRIGHT_QUANTILE level from its histogram, as ``network.bright_level``."""
    n = gray_u8.shape[1] * gray_u8.shape[2]
    offsets = torch.arange(gray_u8.shape[0], device=gray_u8.device)[:, None] * 256
    hist = torch.bincount((gray_u8.flatten(1).long() + offsets).flatten(), minlength=256 * gray_u8.shape[0])
    cum = hist.view(-1, 256).cumsum(1).double()
    return torch.searchsorted(cum, torch.full((gray_u8.shape[0], 1), BRIGHT_QUANTILE * n, dtype=torch.float64,
                                                    device=gray_u8.device)).squeeze(1).float()


def refine_half_px(sizes_px: np.ndarray) -> int:
    """Refinement window half-size from the size head: 3/4 of the median marker size plus 1.5 px."""
    return int(np.clip(np.median(np.asarray(sizes_px).max(axis=1)) * 0.75 + 1.5, 3, 12))


def _centroids_torch(gray: torch.Tensor, image_index: torch.Tensor, uv: torch.Tensor, half_px: int) -> torch.Tensor:
    """``refine.intensity_centroids`` on tensors for a batch: ``gray`` (B, H, W), marker i on image
    ``image_index[i]`` (same windows, background and fallback)."""
    r = half_px
    h, w = gray.shape[1:]
    padded = fn.pad(gray, (r, r, r, r)).double()
    centre = torch.round(uv).long()
    centre[:, 0] = centre[:, 0].clamp(0, w - 1)
    centre[:, 1] = centre[:, 1].clamp(0, h - 1)
    d = torch.arange(-r, r + 1, device=gray.device)
    ys = centre[:, 1, None, None] + d[None, :, None]
    xs = centre[:, 0, None, None] + d[None, None, :]
    win = padded[image_index[:, None, None], ys + r, xs + r]
    ring = torch.cat([win[:, 0], win[:, -1], win[:, 1:-1, 0], win[:, 1:-1, -1]], dim=1)
    k = (ring.shape[1] - 1) // 2
    wgt = (win - torch.kthvalue(ring, k + 1, dim=1).values[:, None, None]).clamp(min=0.0)
    total = wgt.sum(dim=(1, 2))
    ok = total > 0
    safe = torch.where(ok, total, torch.ones_like(total))
    got = torch.stack([(wgt * xs).sum(dim=(1, 2)) / safe, (wgt * ys).sum(dim=(1, 2)) / safe], 1)
    return torch.where(ok[:, None], got, uv)
