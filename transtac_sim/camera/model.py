"""What a camera does to the light reaching it, applied to an ideal pinhole render: lens distortion,
exposure and gain, vignetting, Poisson-Gaussian sensor noise, 8-bit quantisation; each can be switched off.

Pixels follow OpenCV: the centre of the top-left pixel is (0, 0), u right, v down. The renderer makes an
ideal pinhole image with square pixels (``render_K``, ``render_size``) wide enough to hold every ray the
real camera records; ``to_recorded`` resamples it into the recorded (distorted) image with
``cv2.remap``: each recorded pixel's ray comes from an iterative undistortion of its position (checked
to round-trip through ``cv2.projectPoints`` to 1e-6 px). Without distortion (or with it switched off)
and with fx = fy the render is made directly at K and nothing is resampled.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from transtac_sim.rendering.inputs import CameraSpec

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)


@dataclass(frozen=True)
class CameraEffects:
    distortion: bool = True
    exposure: float = 1.0  # linear radiance -> fraction of full well
    gain: float = 1.0  # applied after the noise (amplifies it)
    vignetting: float = 0.0  # strength of the cos^4 fall-off: factor 1 - v + v cos^4(theta)
    noise: bool = True
    full_well_electrons: float = 6000.0
    read_noise_electrons: float = 4.0
    quantize: bool = True


def project(spec: CameraSpec, directions_cam: np.ndarray) -> np.ndarray:
    """Recorded pixels (N, 2) of rays (N, 3) given in the camera's frame (OpenCV projection)."""
    d = np.ascontiguousarray(directions_cam, dtype=np.float64).reshape(-1, 1, 3)
    K, D = np.asarray(spec.K, float), np.asarray(spec.dist, float)
    if spec.model == "fisheye":
        uv, _ = cv2.fisheye.projectPoints(d, np.zeros(3), np.zeros(3), K, D)
    else:
        uv, _ = cv2.projectPoints(d, np.zeros(3), np.zeros(3), K, D)
    return uv.reshape(-1, 2)


def unproject(spec: CameraSpec, uv: np.ndarray) -> np.ndarray:
    """Normalised ideal image coordinates (N, 2) (x/z, y/z) of recorded pixels ``uv`` (N, 2)."""
    p = np.ascontiguousarray(uv, dtype=np.float64).reshape(-1, 1, 2)
    K, D = np.asarray(spec.K, float), np.asarray(spec.dist, float)
    if spec.model == "fisheye":
        xy = cv2.fisheye.undistortPoints(p, K, D, criteria=_CRITERIA)
    else:
        xy = cv2.undistortPoints(p, K, D, criteria=_CRITERIA)
    return xy.reshape(-1, 2)


def invertible_rays(spec: CameraSpec, uv: np.ndarray) -> np.ndarray:
    """Normalised ideal image coordinates (N, 2) of recorded pixels ``uv`` (N, 2); a ValueError where the lens
    distortion does not map them back onto themselves (it folds over: no ray is recorded there)."""
    xy = unproject(spec, uv)
    err = np.abs(project(spec, np.column_stack([xy, np.ones(len(uv))])) - uv).max()
    if not err < 1e-3:
        raise ValueError(f"the lens distortion is not invertible over the image (round trip off by {err:.3g} px)")
    return xy


def image_border(size: tuple[int, int]) -> np.ndarray:
    """The pixel centres (N, 2) along the edges of a ``size`` = (w, h) image: the pixels furthest from the
    principal point, where a distortion folds over first (a cheap check of ``invertible_rays``)."""
    w, h = size
    u, v = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    return np.concatenate([np.column_stack([u, np.zeros(w)]), np.column_stack([u, np.full(w, h - 1.0)]),
                           np.column_stack([np.zeros(h), v]), np.column_stack([np.full(h, w - 1.0), v])])


class CameraModel:
    """One camera's render geometry and its post-render effects."""

    def __init__(self, spec: CameraSpec, effects: CameraEffects = CameraEffects(), max_scale: float = 2.0):
        self.spec, self.effects = spec, effects
        distorted = effects.distortion and np.any(np.asarray(spec.dist) != 0)
        self.recorded = spec if effects.distortion else dataclasses.replace(spec, dist=np.zeros_like(spec.dist))
        w, h = spec.size
        K = np.asarray(spec.K, float)
        self.pixel_xy = invertible_rays(self.recorded, self._recorded_grid())  # (H*W, 2) ideal ray of each pixel
        if not distorted and spec.model == "pinhole" and np.isclose(K[0, 0], K[1, 1]) and K[0, 1] == 0:
            self.render_K, self.render_size, self._maps = K.copy(), (w, h), None
        else:
            self.render_K, self.render_size = self._covering_pinhole(max_scale)
            self._maps = self._remap_maps()
        self._vignette = self._cos4() if effects.vignetting > 0 else None

    def _recorded_grid(self) -> np.ndarray:
        w, h = self.spec.size
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        return np.column_stack([u.ravel(), v.ravel()])

    def _covering_pinhole(self, max_scale: float) -> tuple[np.ndarray, tuple[int, int]]:
        """Square-pixel pinhole K and size covering every recorded pixel (+2 px margin for the bilinear
        lookup); focal length fx, reduced when the image would be over ``max_scale`` times the recorded one."""
        w, h = self.spec.size
        xy = self.pixel_xy
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        f = min(float(self.spec.K[0, 0]), max_scale * w / (hi[0] - lo[0]), max_scale * h / (hi[1] - lo[1]))
        c = -lo * f + 2.0
        size = np.ceil((hi - lo) * f + 4.0).astype(int)
        return np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1.0]]), (int(size[0]), int(size[1]))

    def _remap_maps(self) -> tuple[np.ndarray, np.ndarray]:
        w, h = self.spec.size
        xy = self.pixel_xy
        K = self.render_K
        mx = (K[0, 0] * xy[:, 0] + K[0, 2]).reshape(h, w).astype(np.float32)
        my = (K[1, 1] * xy[:, 1] + K[1, 2]).reshape(h, w).astype(np.float32)
        return mx, my

    def _cos4(self) -> np.ndarray:
        w, h = self.spec.size
        xy = self.pixel_xy
        return (1.0 / (1.0 + (xy**2).sum(axis=1)) ** 2).reshape(h, w)

    def pixel_rays(self) -> np.ndarray:
        """Unit ray (H * W, 3) of every recorded pixel centre, in the camera's frame (row-major)."""
        d = np.column_stack([self.pixel_xy, np.ones(len(self.pixel_xy))])
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def to_recorded(self, pinhole: np.ndarray) -> np.ndarray:
        """Pinhole render (Hr, Wr[, C]) -> image in the recorded geometry (H, W[, C]), float32; pixels
        whose ray is outside the render are 0."""
        img = np.asarray(pinhole, dtype=np.float32)
        if self._maps is None:
            return img
        out = cv2.remap(img, *self._maps, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return out.reshape(out.shape[:2] + img.shape[2:])

    def expose(self, linear: np.ndarray, seed: int | np.random.Generator | None = 0, exposure_scale: float = 1.0) -> np.ndarray:
        """Linear recorded image -> 8-bit (or float in [0, 1] with quantisation off).

        electrons = Poisson(linear * exposure * exposure_scale * vignette * full_well) + Normal(0, read_noise);
        value = gain * electrons / full_well, clipped to [0, 1]; noise seeded by ``seed``. Where the mean
        is >= 30 electrons the Poisson draw is replaced by a Gaussian of the same mean and variance (skew
        below 0.2; twice as fast), below it is exact."""
        e = self.effects
        x = np.asarray(linear, np.float32) * np.float32(e.exposure * exposure_scale)
        if self._vignette is not None:
            v = (1.0 - e.vignetting + e.vignetting * self._vignette).astype(np.float32)
            x = x * (v[..., None] if x.ndim == 3 else v)
        if e.noise:
            rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
            lam = np.clip(x, 0.0, 4.0) * np.float32(e.full_well_electrons)
            low = lam < 30.0
            mean = np.where(low, np.float32(0.0), lam)
            electrons = mean + np.sqrt(mean + np.float32(e.read_noise_electrons**2)) * rng.standard_normal(
                lam.shape, dtype=np.float32)
            electrons[low] += rng.poisson(lam[low])
            x = electrons * np.float32(1.0 / e.full_well_electrons)
        x = np.clip(x * np.float32(e.gain), 0.0, 1.0)
        return np.rint(x * np.float32(255.0)).astype(np.uint8) if e.quantize else x
