"""Exact per-camera marker labels: ``uv`` (the image of the marker centre along its exact refracted
path, in the recorded, distorted image), ``bbox`` (of the projected marker body), ``visible``, and
``uv_centroid`` (intensity centroid of the marker's image in a UV render).

A marker is not ``visible`` in a camera when (a) its centre's image falls outside the image or its ray
is outside the lens model's valid range, (b) its path leaves the gel elsewhere than through the bonded
face (through a side or the deformed contact face: ray/mesh test against the current gel surface) or
misses the backing's outer face, or (c) another marker's body (ellipsoid) lies on the path inside the
gel. Total internal reflection cannot occur on a path leaving the flat stack (see ``refraction``).
Indenters are outside the gel, so they can never be between a marker and a camera behind the backing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from transtac_sim.camera.model import project, unproject
from transtac_sim.labels.refraction import PlanarStack, refracted_paths
from transtac_sim.rendering.geometry import bonded_faces
from transtac_sim.rendering.inputs import CameraSpec, FrameState, SensorScene


@dataclass(frozen=True)
class CameraLabels:
    uv: np.ndarray  # (K, 2) px, OpenCV pixel convention, recorded image
    bbox: np.ndarray  # (K, 4) x0, y0, x1, y1 px, clipped to the image
    visible: np.ndarray  # (K,) bool
    uv_centroid: np.ndarray  # (K, 2) px; NaN where not visible, not rendered, or overlapping another marker

    def as_views(self) -> list[dict]:
        """One ``labels.json`` camera entry per marker (DESIGN.md section 4)."""
        def num(a):
            return None if np.isnan(a).any() else [float(x) for x in a]

        return [{"uv": num(u), "uv_centroid": num(c), "visible": bool(v), "bbox": num(b)}
                for u, c, v, b in zip(self.uv, self.uv_centroid, self.visible, self.bbox, strict=True)]


def _fibonacci_sphere(n: int = 256) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi, theta = np.arccos(1 - 2 * i / n), np.pi * (1 + 5**0.5) * i
    return np.column_stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)])


def image_of_points(spec: CameraSpec, stack: PlanarStack, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Recorded pixels (N, 2) of points inside the gel along their exact refracted paths, and whether each
    ray is in front of the camera and inside the lens model's valid range (projection round-trips)."""
    paths = refracted_paths(stack, spec.centre, points)
    d = paths.directions_left @ np.asarray(spec.R, float).T
    front = d[:, 2] > 1e-6
    uv = project(spec, np.where(front[:, None], d, [0.0, 0.0, 1.0]))
    xy = unproject(spec, uv)
    ok = front & (np.linalg.norm(xy - d[:, :2] / np.where(front, d[:, 2], 1.0)[:, None], axis=1) < 1e-6)
    return uv, ok


def _segments_hit_triangles(p: np.ndarray, q: np.ndarray, tri: np.ndarray, eps: float = 1e-9) -> np.ndarray:
    """(K,) whether segment p_k -> q_k crosses any triangle of ``tri`` (F, 3, 3) strictly between its ends
    (Moller-Trumbore on the segment/triangle pairs whose bounding boxes overlap)."""
    seg_lo, seg_hi = np.minimum(p, q), np.maximum(p, q)
    tri_lo, tri_hi = tri.min(axis=1), tri.max(axis=1)
    k, f = np.nonzero(np.all((tri_lo[None] <= seg_hi[:, None]) & (tri_hi[None] >= seg_lo[:, None]), axis=-1))
    t0, e1, e2 = tri[f, 0], tri[f, 1] - tri[f, 0], tri[f, 2] - tri[f, 0]
    d = q[k] - p[k]
    h = np.cross(d, e2)
    a = np.einsum("ni,ni->n", h, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(np.abs(a) < 1e-15, np.nan, 1.0 / a)
        s = p[k] - t0
        u = np.einsum("ni,ni->n", s, h) * inv
        qv = np.cross(s, e1)
        v = np.einsum("ni,ni->n", d, qv) * inv
        t = np.einsum("ni,ni->n", e2, qv) * inv
        crosses = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > eps) & (t < 1 - eps)
    hit = np.zeros(len(p), bool)
    hit[k[crosses]] = True
    return hit


def _in_triangles_xy(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """(N,) whether the xy of ``points`` lies in the xy projection of any triangle of ``tri`` (F, 3, 3)."""
    a, b, c = tri[:, 0, :2], tri[:, 1, :2], tri[:, 2, :2]
    p = points[:, None, :2]

    def side(x, y):
        return (y[..., 0] - x[..., 0]) * (p[..., 1] - x[..., 1]) - (y[..., 1] - x[..., 1]) * (p[..., 0] - x[..., 0])

    s1, s2, s3 = side(a, b), side(b, c), side(c, a)
    return (((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))).any(axis=1)


def _blocked_by_markers(p: np.ndarray, q: np.ndarray, centres: np.ndarray, shape_inv: np.ndarray) -> np.ndarray:
    """(K,) whether the gel segment p_k -> q_k passes through another marker's ellipsoid
    {x : |A_j (x - c_j)| <= 1}, ``shape_inv`` = A_j (K, 3, 3)."""
    a = np.einsum("jab,kjb->kja", shape_inv, p[:, None, :] - centres[None])  # segment start in j's unit frame
    d = np.einsum("jab,kb->kja", shape_inv, q - p)
    t = np.clip(-np.einsum("kja,kja->kj", a, d) / np.maximum(np.einsum("kja,kja->kj", d, d), 1e-300), 0.0, 1.0)
    dist = np.linalg.norm(a + t[..., None] * d, axis=-1)
    np.fill_diagonal(dist, np.inf)
    return (dist < 1.0).any(axis=1)


def marker_labels(spec: CameraSpec, stack: PlanarStack, centres: np.ndarray, radius: float,
                  deformation: np.ndarray | None, gel_vertices: np.ndarray, gel_faces: np.ndarray,
                  bonded: np.ndarray, backing_lo: np.ndarray, backing_hi: np.ndarray) -> CameraLabels:
    """Labels of markers (centres (K, 3), ``radius`` mm, optional deformation gradients (K, 3, 3)) in one
    camera whose recorded geometry is ``spec``; ``gel_vertices``/``gel_faces`` is the current gel surface
    and ``bonded`` the mask of its faces on the bonded plane. ``uv_centroid`` is NaN (see ``add_centroids``)."""
    c = np.asarray(centres, float)
    K = len(c)
    F = np.broadcast_to(np.eye(3), (K, 3, 3)) if deformation is None else np.asarray(deformation, float)
    w, h = spec.size
    uv, ok = image_of_points(spec, stack, c)
    body = c[:, None, :] + radius * np.einsum("kij,nj->kni", F, _fibonacci_sphere())
    rim_uv, _ = image_of_points(spec, stack, np.maximum(body.reshape(-1, 3), [-np.inf, -np.inf, stack.z_bond]))
    rim_uv = rim_uv.reshape(K, -1, 2)
    bbox = np.concatenate([rim_uv.min(axis=1), rim_uv.max(axis=1)], axis=1)
    bbox = np.clip(bbox, -0.5, [w - 0.5, h - 0.5, w - 0.5, h - 0.5])
    inside = ok & (uv[:, 0] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= h - 0.5)

    paths = refracted_paths(stack, spec.centre, c)
    v, f = np.asarray(gel_vertices, float), np.asarray(gel_faces)
    through_bond = _in_triangles_xy(paths.at_bond, v[f[bonded]])
    through_back = np.all((paths.at_back[:, :2] >= backing_lo[:2]) & (paths.at_back[:, :2] <= backing_hi[:2]), axis=1)
    leaves_gel = _segments_hit_triangles(c, paths.at_bond, v[f[~bonded]])
    blocked = _blocked_by_markers(c, paths.at_bond, c, np.linalg.inv(radius * F))
    visible = inside & through_bond & through_back & ~leaves_gel & ~blocked
    return CameraLabels(uv, bbox, visible, np.full((K, 2), np.nan))


def add_centroids(labels: CameraLabels, uv_linear: np.ndarray, pad_px: float = 2.0) -> CameraLabels:
    """``uv_centroid`` of each visible marker: intensity (luminance) centroid of a linear UV image in the
    recorded geometry over the marker's bbox grown by ``pad_px``, less the median of that window's border.
    NaN when the window meets another visible marker's bbox (its light would bias the centroid)."""
    img = np.asarray(uv_linear, np.float64)
    lum = img @ [0.2126, 0.7152, 0.0722] if img.ndim == 3 else img
    h, w = lum.shape
    lo = np.floor(labels.bbox[:, :2] - pad_px + 0.5).astype(int).clip(0, [w - 1, h - 1])
    hi = np.ceil(labels.bbox[:, 2:] + pad_px - 0.5).astype(int).clip(0, [w - 1, h - 1])
    vis = np.flatnonzero(labels.visible)
    cen = np.full_like(labels.uv, np.nan)
    for k in vis:
        others = vis[vis != k]
        b = labels.bbox[others]
        if np.any((b[:, 0] <= hi[k, 0]) & (b[:, 2] >= lo[k, 0]) & (b[:, 1] <= hi[k, 1]) & (b[:, 3] >= lo[k, 1])):
            continue
        win = lum[lo[k, 1] : hi[k, 1] + 1, lo[k, 0] : hi[k, 0] + 1]
        border = np.concatenate([win[0], win[-1], win[:, 0], win[:, -1]])
        wgt = np.clip(win - np.median(border), 0.0, None)
        if wgt.sum() <= 0:
            continue
        vv, uu = np.mgrid[lo[k, 1] : hi[k, 1] + 1, lo[k, 0] : hi[k, 0] + 1]
        cen[k] = [(wgt * uu).sum() / wgt.sum(), (wgt * vv).sum() / wgt.sum()]
    return CameraLabels(labels.uv, labels.bbox, labels.visible, cen)


def planar_stack(scene: SensorScene) -> PlanarStack:
    """The flat layers of ``scene``: backing box z range and the gel's bonded plane."""
    b = scene.backing
    if not np.isclose(scene.gel.bonded_z, b.hi[2]):
        raise ValueError("the gel's bonded face must lie on the backing")
    return PlanarStack(float(b.lo[2]), float(b.hi[2]), b.ior, scene.gel.ior)


def frame_labels(scene: SensorScene, frame: FrameState | None, cameras: dict[str, CameraSpec],
                 uv_linear: dict[str, np.ndarray] | None = None) -> dict[str, CameraLabels]:
    """Labels of every marker in each of ``cameras`` (their recorded geometry, e.g. ``CameraModel.recorded``)
    for the scene moved to ``frame``; ``uv_centroid`` from ``uv_linear[camera]`` where given."""
    frame = frame or FrameState()
    gv = scene.gel.vertices if frame.gel_vertices is None else frame.gel_vertices
    centres = scene.markers.centres if frame.marker_centres is None else frame.marker_centres
    F = scene.markers.deformation if frame.marker_deformation is None else frame.marker_deformation
    bonded = bonded_faces(scene.gel.vertices, scene.gel.faces)
    stack = planar_stack(scene)
    out = {}
    for name, spec in cameras.items():
        lab = marker_labels(spec, stack, centres, scene.markers.radius, F, gv, scene.gel.faces, bonded,
                            np.asarray(scene.backing.lo, float), np.asarray(scene.backing.hi, float))
        if uv_linear is not None and name in uv_linear:
            lab = add_centroids(lab, uv_linear[name])
        out[name] = lab
    return out
