"""``transtac-sim train-detector``: train MarkerNet on generated datasets.

Data: every complete frame's UV images (both cameras) with the visible markers' ``uv_centroid`` and boxes
from ``labels.json``. Split by sequence: in each dataset, every 8th sequence (sorted by name: the 8th,
16th, ...) is validation, the rest training, so no sequence straddles the split.
Each step draws ``batch`` random crops (``augment``), builds the targets (``targets``) and takes one AdamW
step on the loss (``loss``) with a linear warm-up over the first 5 % of the steps and a cosine decay; mixed precision on a GPU (float16 with
loss scaling). Every ``eval_every`` steps and at the end it measures precision and recall at 2 px on the
validation images (full size, raw offset head, no refinement).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from transtac_sim.perception.dataset_files import labelled_images, sequences
from transtac_sim.perception.detection.model_file import save_model
from transtac_sim.perception.detection.network import MarkerNet, decode, normalise
from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.perception.evaluation.detection import DetectionTally
from transtac_sim.perception.images import read_color_image
from transtac_sim.perception.training.augment import AugmentParams, photometric, random_crop
from transtac_sim.perception.training.loss import correlation_term, focal_loss, masked_l1
from transtac_sim.perception.training.targets import make_targets

VAL_EVERY_NTH_SEQUENCE = 8


@dataclass(frozen=True)
class TrainConfig:
    steps: int = 3000
    batch: int = 16
    crop_px: int = 128
    learning_rate: float = 3e-3
    width: int = 16
    context: bool = False  # the stride-16 level of MarkerNet
    correlation_weight: float = 0.0  # lambda_corr; 0 leaves the term out
    device: str = "auto"
    amp: bool = True  # mixed precision (used on CUDA only)
    seed: int = 0
    eval_every: int = 500
    max_images: int | None = None  # cap on training images (tests)


@dataclass
class Sample:
    image: np.ndarray
    white: np.ndarray | None
    uv: np.ndarray
    size: np.ndarray
    name: str


@dataclass
class TrainReport:
    model: Path
    train_images: int
    val_images: int
    losses: list[float] = field(default_factory=list)  # mean loss per eval interval
    val: list[dict] = field(default_factory=list)  # metrics per evaluation, with "step"
    seconds: float = 0.0
    device: str = "cpu"


def load_samples(datasets: list[Path], max_images: int | None = None) -> tuple[list[Sample], list[Sample]]:
    train, val = [], []
    for ds in datasets:
        seqs = sequences(ds)
        val_seqs = {s for i, s in enumerate(seqs) if i % VAL_EVERY_NTH_SEQUENCE == VAL_EVERY_NTH_SEQUENCE - 1}
        for li in labelled_images(ds):
            t = li.truth
            s = Sample(read_color_image(li.uv_path), read_color_image(li.white_path) if li.white_path else None,
                       t.uv, np.stack([t.bbox[:, 2] - t.bbox[:, 0], t.bbox[:, 3] - t.bbox[:, 1]], 1),
                       str(li.uv_path))
            (val if li.sequence in val_seqs else train).append(s)
    if not train:
        raise PerceptionInputError(", ".join(map(str, datasets)), "no labelled UV images to train on",
                                   "pass datasets written by `transtac-sim generate` with UV images and labels")
    if max_images:
        train, val = train[:max_images], val[: max(1, max_images // 4)]
    return train, val


def _batch(samples: list[Sample], whites: list[np.ndarray], cfg: TrainConfig, rng: np.random.Generator,
           aug: AugmentParams):
    images, targets = [], []
    for _ in range(cfg.batch):
        s = samples[int(rng.integers(len(samples)))]
        white = s.white if s.white is not None else (whites[int(rng.integers(len(whites)))] if whites else None)
        img, wcrop, uv, size = random_crop(s.image, white, s.uv, s.size, cfg.crop_px, rng, aug)
        images.append(normalise(photometric(img, wcrop, rng, aug)))
        targets.append(make_targets(uv, size, img.shape[:2]))
    stack = {k: torch.from_numpy(np.stack([t[k] for t in targets])) for k in ("heat", "offset", "size", "mask")}
    return torch.from_numpy(np.stack(images)), stack, [t["centres"] for t in targets]


def evaluate(net: MarkerNet, samples: list[Sample], device: str) -> dict:
    tally = DetectionTally(radii_px=(2.0,))
    net.eval()
    with torch.no_grad():
        for s in samples:
            heat, off, size, _ = net(torch.from_numpy(normalise(s.image)[None]).to(device))
            uv, _, _ = decode(heat[0].float().cpu().numpy(), off[0].float().cpu().numpy(), size[0].float().cpu().numpy())
            tally.add(uv, s.uv)
    net.train()
    return tally.summary()


def train_detector(datasets: list[Path], out: Path, cfg: TrainConfig = TrainConfig(),
                   progress: Callable[[int, float, dict | None], None] | None = None,
                   command: str = "") -> TrainReport:
    """Train, write the model (``out``, .pt and .onnx) and return the report. ``progress(step, loss, val)``
    is called every 10 steps and after each evaluation."""
    t_start = time.perf_counter()
    device = ("cuda" if torch.cuda.is_available() else "cpu") if cfg.device == "auto" else cfg.device
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    multiple = 16 if cfg.context else 8  # MarkerNet's coarsest stride (network.py)
    if cfg.crop_px % multiple:
        raise ValueError(f"crop {cfg.crop_px} px: must be a multiple of {multiple}"
                         + (" with the context level (--context)" if cfg.context else ""))
    train, val = load_samples([Path(d) for d in datasets], cfg.max_images)
    whites = [s.white for s in train if s.white is not None]
    sizes = sorted({(s.image.shape[1], s.image.shape[0]) for s in train + val})
    odd = [f"{w}x{h}" for w, h in sizes if w % multiple or h % multiple]
    if odd:
        raise PerceptionInputError(", ".join(map(str, datasets)), f"images of {', '.join(odd)} px: MarkerNet needs "
                                   f"widths and heights that are multiples of {multiple}",
                                   "render the datasets at such a size" + (", or train without --context"
                                                                          if cfg.context else ""))
    net = MarkerNet(cfg.width, cfg.context).to(device).train()
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.learning_rate, weight_decay=1e-4)
    warmup = max(1, cfg.steps // 20)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda k: min((k + 1) / warmup, 0.5 * (1 + np.cos(np.pi * k / cfg.steps))))
    amp = cfg.amp and device.startswith("cuda")
    scaler = torch.amp.GradScaler("cuda", enabled=amp)
    aug = AugmentParams()
    report = TrainReport(Path(out), len(train), len(val), device=device)
    running = []
    for step in range(1, cfg.steps + 1):
        x, tgt, centres = _batch(train, whites, cfg, rng, aug)
        x, tgt = x.to(device), {k: v.to(device) for k, v in tgt.items()}
        with torch.autocast(device_type="cuda", dtype=torch.float16, enabled=amp):
            heat, off, size, feats = net(x)
        loss = (focal_loss(heat, tgt["heat"]) + masked_l1(off, tgt["offset"], tgt["mask"])
                + 0.1 * masked_l1(size, tgt["size"], tgt["mask"]))
        if cfg.correlation_weight > 0:
            loss = loss + cfg.correlation_weight * correlation_term(feats, centres)
        opt.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        scaler.step(opt)
        scaler.update()
        sched.step()
        running.append(loss.item())
        metrics = None
        if val and (step % cfg.eval_every == 0 or step == cfg.steps):
            metrics = {"step": step, **evaluate(net, val, device)}
            report.val.append(metrics)
            report.losses.append(float(np.mean(running[-cfg.eval_every:])))
        if progress and (step % 10 == 0 or metrics):
            progress(step, float(np.mean(running[-10:])), metrics)
    report.seconds = time.perf_counter() - t_start
    provenance = {"datasets": [str(d) for d in datasets], "config": asdict(cfg), "command": command,
                  "train_images": len(train), "val_images": len(val), "val": report.val[-1] if report.val else None,
                  "seconds": report.seconds, "device": device, "torch": str(torch.__version__)}
    save_model(Path(out), net.cpu(), sizes, provenance)
    return report
