"""Pictures for people: an image with its detected markers circled; a reconstructed frame (matches on both
views and the surface coloured by depth), as a PNG or an MP4 of the sequence."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from transtac_sim.writer.atomic import atomic_write


def detection_preview(image_bgr: np.ndarray, uv: np.ndarray, path: Path, scale: int = 2) -> Path:
    """PNG of ``image_bgr`` brightened to its 99.9th percentile, enlarged ``scale`` times, with a circle at
    each ``uv`` (px)."""
    img = cv2.resize(_brightened(image_bgr), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    for u, v in np.asarray(uv).reshape(-1, 2):
        c = (int(round((u + 0.5) * scale - 0.5)), int(round((v + 0.5) * scale - 0.5)))
        cv2.circle(img, c, 6 * scale, (0, 0, 255), 1, cv2.LINE_AA)
    return write_png(path, img)


def _brightened(image_bgr: np.ndarray) -> np.ndarray:
    img = image_bgr.astype(np.float32)
    return np.clip(img * (230.0 / max(float(np.percentile(img, 99.9)), 1.0)), 0, 255).astype(np.uint8)


def depth_panel(shape: tuple[int, int], left_uv: np.ndarray, z_mm: np.ndarray,
                dense_z_mm: np.ndarray | None = None) -> np.ndarray:
    """A BGR picture (h, w) of depth coloured with the turbo map (near red, far blue): the dense depth when
    given (on its own grid, resized), else the markers' z interpolated linearly between them (scipy's
    griddata, inside their convex hull), coloured over its 5th to 95th percentile (written in mm)."""
    h, w = shape
    if dense_z_mm is not None:
        z = cv2.resize(np.where(np.isfinite(dense_z_mm), dense_z_mm, np.nan).astype(np.float32), (w, h),
                       interpolation=cv2.INTER_NEAREST)
    elif len(z_mm) >= 3:
        from scipy.interpolate import griddata

        vv, uu = np.mgrid[0:h, 0:w]
        try:
            z = griddata(np.asarray(left_uv, float), np.asarray(z_mm, float), (uu, vv), method="linear")
        except Exception:  # points on a line: scipy's Qhull cannot triangulate them
            z = np.full((h, w), np.nan)
    else:
        z = np.full((h, w), np.nan)
    ok = np.isfinite(z)
    panel = np.zeros((h, w, 3), np.uint8)
    if ok.any():
        lo, hi = np.percentile(z[ok], [5, 95])
        scaled = np.clip((hi - np.where(ok, z, hi)) / max(hi - lo, 1e-6), 0, 1)
        panel = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_TURBO)
        panel[~ok] = 0
        cv2.putText(panel, f"depth {lo:.2f} (red) .. {hi:.2f} (blue) mm", (8, h - 10), cv2.FONT_HERSHEY_SIMPLEX,
                    0.5, (255, 255, 255), 1, cv2.LINE_AA)
    return panel


def reconstruction_panel(left: np.ndarray, right: np.ndarray, uv_l: np.ndarray, uv_r: np.ndarray,
                         pairs: np.ndarray, xyz_mm: np.ndarray, dense_z_mm: np.ndarray | None = None) -> np.ndarray:
    """Both views side by side (brightened), detections circled, matches joined by lines, and the depth
    panel (``depth_panel``) of the matched markers' left positions and z (or the dense depth) beside them."""
    both = _brightened(np.hstack([left, right]))
    w = left.shape[1]
    for u, v in uv_l:
        cv2.circle(both, (int(round(u)), int(round(v))), 5, (0, 0, 255), 1, cv2.LINE_AA)
    for u, v in uv_r:
        cv2.circle(both, (int(round(u)) + w, int(round(v))), 5, (0, 0, 255), 1, cv2.LINE_AA)
    for i, j in pairs:
        a = (int(round(uv_l[i][0])), int(round(uv_l[i][1])))
        b = (int(round(uv_r[j][0])) + w, int(round(uv_r[j][1])))
        cv2.line(both, a, b, (255, 200, 0), 1, cv2.LINE_AA)
    matched_uv = uv_l[pairs[:, 0]] if len(pairs) else np.zeros((0, 2))
    depth = depth_panel(left.shape[:2], matched_uv, np.asarray(xyz_mm).reshape(-1, 3)[:, 2], dense_z_mm)
    return np.hstack([both, depth])


def write_png(path: Path, image_bgr: np.ndarray) -> Path:
    ok, buf = cv2.imencode(".png", image_bgr)
    return atomic_write(Path(path), lambda f: f.write(buf.tobytes()))


def write_video(path: Path, frames_bgr: list[np.ndarray], fps: float = 10.0) -> Path:
    """An MP4 (OpenCV's mp4v codec) of equally sized BGR frames, written to a temporary name and renamed."""
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    h, w = frames_bgr[0].shape[:2]
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    if not writer.isOpened():
        raise OSError(f"{path}: OpenCV cannot write an MP4 video here")
    for f in frames_bgr:
        writer.write(f)
    writer.release()
    tmp.replace(path)
    return path
