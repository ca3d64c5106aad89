"""Augmentations a real camera needs, applied to a training crop and its marker centres together:
a small affine change (rotation, scale, shift), white-light leak (a fraction of a white-light image added),
gain, blur, sensor noise, and 8-bit quantisation. All draws come from the ``rng`` passed in."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class AugmentParams:
    rotation_deg: float = 15.0
    scale: tuple[float, float] = (0.9, 1.1)
    gain: tuple[float, float] = (0.4, 2.5)
    leak_probability: float = 0.35
    leak_fraction: tuple[float, float] = (0.05, 0.8)
    blur_probability: float = 0.3
    blur_sigma_px: tuple[float, float] = (0.3, 1.1)
    noise_probability: float = 0.6
    noise_sigma: tuple[float, float] = (0.3, 2.5)  # grey levels


def random_crop(image: np.ndarray, white: np.ndarray | None, uv: np.ndarray, size_px: np.ndarray, crop: int,
                rng: np.random.Generator, p: AugmentParams) -> tuple[np.ndarray, np.ndarray | None, np.ndarray, np.ndarray]:
    """A ``crop`` x ``crop`` window of the image (and of the white image), turned and scaled about its centre;
    returns both crops, the markers' centres in crop pixels and their scaled sizes."""
    h, w = image.shape[:2]
    cx, cy = rng.uniform(crop / 2, w - crop / 2), rng.uniform(crop / 2, h - crop / 2)
    s = rng.uniform(*p.scale)
    m = cv2.getRotationMatrix2D((cx, cy), rng.uniform(-p.rotation_deg, p.rotation_deg), s)
    m[:, 2] += [crop / 2 - cx, crop / 2 - cy]
    warp = lambda im: cv2.warpAffine(im, m, (crop, crop), flags=cv2.INTER_LINEAR, borderValue=0)  # noqa: E731
    uv_c = np.asarray(uv).reshape(-1, 2) @ m[:, :2].T + m[:, 2]
    return warp(image), (warp(white) if white is not None else None), uv_c, np.asarray(size_px) * s


def photometric(image: np.ndarray, white: np.ndarray | None, rng: np.random.Generator, p: AugmentParams) -> np.ndarray:
    """Leak, gain, blur, noise and quantisation of an 8-bit crop; returns uint8."""
    img = image.astype(np.float32)
    if white is not None and rng.random() < p.leak_probability:
        img += rng.uniform(*p.leak_fraction) * white.astype(np.float32)
    img *= rng.uniform(*p.gain)
    if rng.random() < p.blur_probability:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(*p.blur_sigma_px))
    if rng.random() < p.noise_probability:
        img += rng.normal(0.0, rng.uniform(*p.noise_sigma), img.shape).astype(np.float32)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
