"""Dense stereo on the white-light pair and its alignment to metric anchors (markers, object features).

Dense points (``dense_points``): both images rectified (``StereoCalibration.rectification_maps``), a
disparity per rectified left pixel from either OpenCV's semi-global matching (``"sgbm"``, no weights: it
searches d_ref - ``farther_px`` .. d_ref + ``nearer_px``, d_ref the markers' median rectified disparity, so
objects up to a few centimetres beyond the gel are found) or a learned stereo
model the user has as a local ONNX file (``OnnxStereo``: FoundationStereo in the TransTac paper, exported by
its own scripts; nothing is downloaded), then ``cv2.reprojectImageTo3D`` with Q gives points in the
rectified left frame, turned into the left camera frame by R1^T (x_rect = R1 x_left). These are pinhole
points: through the backing and gel they are off by a distortion of a few millimetres.

Fusion: a similarity x' = s R x + t from the dense map's pinhole geometry to the anchors' metric 3D
positions, fitted by RANSAC (scikit-image's ``ransac``) around Umeyama's least-squares similarity
(``SimilarityTransform``; ``fit_similarity``), a pair an inlier when its residual is within its own
tolerance (distance-aware, ``stereo.anchors``) and samples implying a scale outside 0.8..1.25 rejected.
The source point of an anchor is either the dense map's point under it (``align_to_anchors``: the median of
the valid points in a 3x3 window at its rectified left position; right for a learned model, whose output
may carry its own bias) or, for SGBM, the pinhole (linear) triangulation of the anchor's own pixel pair,
the same geometry as SGBM's points without their noise on small marker dots (``perception.fuse``).
Applying it to every dense point gives the fused point cloud and depth map (z in the left camera frame,
mm, on the rectified left image grid).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from transtac_sim.perception.errors import PerceptionInputError
from transtac_sim.perception.stereo.calibration import StereoCalibration


@dataclass(frozen=True)
class DensePoints:
    xyz_mm: np.ndarray  # (H, W, 3) left camera frame, on the rectified left grid
    valid: np.ndarray  # (H, W) bool


@dataclass(frozen=True)
class Alignment:
    scale: float
    rotation: np.ndarray  # (3, 3)
    translation_mm: np.ndarray  # (3,)
    pairs: int
    inliers: int
    rms_mm: float  # of the inlier pairs after alignment

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        return self.scale * xyz @ self.rotation.T + self.translation_mm


def _grey(image_bgr: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr


def stretched_grey(image_bgr: np.ndarray) -> np.ndarray:
    """8-bit grey image scaled so that its 99.9th percentile is 230 (dim white-light frames use the range)."""
    g = _grey(image_bgr).astype(np.float32)
    return np.clip(g * (230.0 / max(float(np.percentile(g, 99.9)), 1.0)), 0, 255).astype(np.uint8)


def sgbm_disparity(left_rect: np.ndarray, right_rect: np.ndarray, disparity_px: float, nearer_px: int = 32,
                   farther_px: int = 128, block_px: int = 5) -> np.ndarray:
    """Disparity (H, W) px of rectified 8-bit images by SGBM from ``disparity_px - farther_px`` (objects
    beyond the gel) to ``disparity_px + nearer_px``; NaN where unmatched."""
    lo = int(np.floor(disparity_px - farther_px))
    count = int(np.ceil((farther_px + nearer_px) / 16.0)) * 16
    sgbm = cv2.StereoSGBM_create(minDisparity=lo, numDisparities=count, blockSize=block_px,
                                 P1=8 * block_px**2, P2=32 * block_px**2, uniquenessRatio=5,
                                 speckleWindowSize=50, speckleRange=2, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    left, right = stretched_grey(left_rect), stretched_grey(right_rect)
    # SGBM leaves the leftmost minDisparity + numDisparities columns unmatched: pad both images by that
    # much on the left (the right image's padding is black, where no right pixel exists anyway)
    pad = max(lo + count, 0)
    left_p, right_p = (cv2.copyMakeBorder(g, 0, 0, pad, 0, cv2.BORDER_CONSTANT, value=0) for g in (left, right))
    d = sgbm.compute(left_p, right_p)[:, pad:].astype(np.float32) / 16.0
    return np.where((d >= lo) & textured(left, block_px), d, np.nan)


def textured(grey: np.ndarray, block_px: int, min_contrast: float = 6.0) -> np.ndarray:
    """Pixels whose ``block_px`` window has a grey-level standard deviation of at least ``min_contrast``
    (of 255) above what the noise alone gives: where block matching has something to match."""
    g = cv2.GaussianBlur(grey.astype(np.float32), (3, 3), 0)
    mean = cv2.blur(g, (block_px, block_px))
    std = np.sqrt(np.maximum(cv2.blur(g * g, (block_px, block_px)) - mean * mean, 0.0))
    return std >= min_contrast


class OnnxStereo:
    """A learned stereo model from a local ONNX file: inputs ``left`` and ``right`` (the first two inputs),
    1 x 3 x H x W float32 RGB in 0..255 of the rectified pair; first output the left disparity in px,
    shaped (1, 1, H, W), (1, H, W) or (H, W). A model exported at a fixed size gets the images resized to it
    and its disparity scaled back. Missing or unreadable files raise ``PerceptionInputError``."""

    def __init__(self, path: Path | str) -> None:
        path = Path(path)
        if not path.is_file():
            raise PerceptionInputError(path, "stereo model file not found",
                                       "export the model's weights to ONNX on your machine and pass that file "
                                       "(weights are never downloaded), or use --dense sgbm")
        import onnxruntime as ort

        try:
            self.session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types for a bad file
            raise PerceptionInputError(path, f"not a readable ONNX model ({type(e).__name__})",
                                       "pass an ONNX export of the stereo model") from None
        inputs = self.session.get_inputs()
        if len(inputs) < 2 or len(inputs[0].shape) != 4:
            raise PerceptionInputError(path, f"the model has {len(inputs)} input(s) "
                                       f"{[tuple(i.shape) for i in inputs]}", "it needs left and right, each 1x3xHxW")
        self.path = path
        self.names = [inputs[0].name, inputs[1].name]
        h, w = inputs[0].shape[2:]
        self.fixed_size = (w, h) if isinstance(h, int) and isinstance(w, int) else None

    def __call__(self, left_rect: np.ndarray, right_rect: np.ndarray) -> np.ndarray:
        h, w = left_rect.shape[:2]
        size = self.fixed_size or (w, h)

        def tensor(im: np.ndarray) -> np.ndarray:
            rgb = cv2.cvtColor(im, cv2.COLOR_BGR2RGB) if im.ndim == 3 else np.repeat(im[:, :, None], 3, axis=2)
            rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_LINEAR) if size != (w, h) else rgb
            return np.ascontiguousarray(rgb.transpose(2, 0, 1)[None], dtype=np.float32)

        out = self.session.run(None, dict(zip(self.names, (tensor(left_rect), tensor(right_rect)), strict=True)))[0]
        d = np.asarray(out, np.float32).reshape(size[1], size[0])
        if size != (w, h):
            d = cv2.resize(d, (w, h), interpolation=cv2.INTER_LINEAR) * (w / size[0])
        return d


def dense_points(calib: StereoCalibration, left_bgr: np.ndarray, right_bgr: np.ndarray, disparity_px: float,
                 model: OnnxStereo | None = None, nearer_px: int = 32, farther_px: int = 128,
                 block_px: int = 5) -> DensePoints:
    """Dense points of a recorded white-light pair: SGBM around ``disparity_px``, or ``model``."""
    maps = calib.rectification_maps
    left = cv2.remap(left_bgr, *maps["left"], cv2.INTER_LINEAR)
    right = cv2.remap(right_bgr, *maps["right"], cv2.INTER_LINEAR)
    disparity = model(left, right) if model is not None else sgbm_disparity(
        left, right, disparity_px, nearer_px, farther_px, block_px)
    valid = np.isfinite(disparity) & (disparity > 0)
    xyz_rect = cv2.reprojectImageTo3D(np.where(valid, disparity, 1.0).astype(np.float32), calib.rectification.Q)
    xyz = xyz_rect @ calib.rectification.R1  # row vectors: x_left = R1^T x_rect
    return DensePoints(xyz.astype(np.float64), valid)


class _ToleratedSimilarity:
    """scikit-image's SimilarityTransform for ``ransac``, with each pair's residual divided by its tolerance
    (the 4th column of ``dst``), so that RANSAC's threshold 1 means 'within its own tolerance'."""

    def __init__(self, transform) -> None:
        self.transform = transform
        self.params = transform.params

    @classmethod
    def from_estimate(cls, src: np.ndarray, dst: np.ndarray):
        from skimage.transform import SimilarityTransform

        fitted = SimilarityTransform.from_estimate(src, dst[:, :3])
        return cls(fitted) if fitted else fitted  # a failed estimation is falsy: ransac skips it

    def residuals(self, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
        return self.transform.residuals(src, dst[:, :3]) / dst[:, 3]


def _plausible_scale(params: np.ndarray, lo: float = 0.8, hi: float = 1.25) -> bool:
    """Refraction changes the pinhole points' scale by a few per cent, not more: a sample of three anchors
    implying a scale outside [lo, hi] (nearly collinear, or a wrong dense point) is not a candidate."""
    return lo <= float(np.cbrt(np.linalg.det(params[:3, :3]))) <= hi


def fit_similarity(src_mm: np.ndarray, dst_mm: np.ndarray, tolerance_mm: np.ndarray | float = 0.3,
                   seed: int = 0) -> Alignment | None:
    """RANSAC + Umeyama similarity dst ~ s R src + t of point pairs (K, 3), a pair an inlier within its own
    ``tolerance_mm``; None with fewer than 3 pairs or no consistent sample."""
    from skimage.measure import ransac

    src = np.asarray(src_mm, float).reshape(-1, 3)
    dst = np.column_stack([np.asarray(dst_mm, float).reshape(-1, 3),
                           np.broadcast_to(np.asarray(tolerance_mm, float), (len(src),))])
    if len(src) < 3:
        return None
    model, inliers = ransac((src, dst), _ToleratedSimilarity, min_samples=3, residual_threshold=1.0,
                            max_trials=500, rng=seed, is_model_valid=lambda m, *_: bool(m) and _plausible_scale(m.params))
    if not model or inliers is None or inliers.sum() < 3:
        return None
    m = model.params
    scale = float(np.cbrt(np.linalg.det(m[:3, :3])))
    rot = m[:3, :3] / scale
    res = np.linalg.norm(scale * src[inliers] @ rot.T + m[:3, 3] - dst[inliers, :3], axis=1)
    return Alignment(scale, rot, m[:3, 3].copy(), len(src), int(inliers.sum()), float(np.sqrt(np.mean(res**2))))


def align_to_anchors(dense: DensePoints, calib: StereoCalibration, left_uv: np.ndarray, anchors_xyz_mm: np.ndarray,
                     tolerance_mm: np.ndarray | float = 0.3, seed: int = 0) -> Alignment | None:
    """The similarity taking the dense map's points onto anchors (3D points ``anchors_xyz_mm`` seen at
    recorded left pixels ``left_uv``), each dense point the median of the valid ones in the 3x3 window at the
    anchor's rectified position; None with fewer than 3 usable pairs. ``tolerance_mm``: per anchor or one."""
    h, w = dense.valid.shape
    left_uv = np.asarray(left_uv, dtype=np.float64).reshape(-1, 2)
    anchors = np.asarray(anchors_xyz_mm, float).reshape(-1, 3)
    tol = np.broadcast_to(np.asarray(tolerance_mm, float), (len(anchors),))
    rect = np.rint(calib.rectified(left_uv, "left")).astype(int) if len(left_uv) else np.zeros((0, 2), int)
    src, dst, keep = [], [], []
    for (u, v), x, t in zip(rect, anchors, tol, strict=True):
        y0, y1, x0, x1 = max(v - 1, 0), min(v + 2, h), max(u - 1, 0), min(u + 2, w)
        if y0 >= y1 or x0 >= x1:
            continue
        ok = dense.valid[y0:y1, x0:x1]
        if ok.any():
            src.append(np.median(dense.xyz_mm[y0:y1, x0:x1][ok], axis=0))
            dst.append(x)
            keep.append(t)
    return fit_similarity(np.array(src).reshape(-1, 3), np.array(dst).reshape(-1, 3), np.array(keep), seed)


def write_ply(path, xyz_mm: np.ndarray) -> None:
    """Binary little-endian PLY of points (N, 3), float32, mm."""
    from transtac_sim.writer.atomic import atomic_write

    pts = np.ascontiguousarray(xyz_mm, dtype="<f4").reshape(-1, 3)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment units mm, left camera frame\nelement vertex {len(pts)}\n"
              "property float x\nproperty float y\nproperty float z\nend_header\n").encode()
    atomic_write(Path(path), lambda f: (f.write(header), f.write(pts.tobytes())))


def write_depth_exr(path, depth_mm: np.ndarray) -> None:
    """Single-channel float32 EXR named ``Z`` (mm), +inf where there is no point (as the datasets' depth)."""
    import OpenEXR

    from transtac_sim.writer.atomic import atomic_write

    atomic_write(Path(path), lambda f: OpenEXR.File(
        {"type": OpenEXR.scanlineimage, "compression": OpenEXR.ZIP_COMPRESSION},
        {"Z": np.ascontiguousarray(depth_mm, dtype=np.float32)}).write(f))
