"""Depth AOV: for every recorded pixel, the z-depth (mm, in that camera's frame) of the first
non-transparent surface along the camera ray, the ray refracted (or, past the critical angle, reflected)
deterministically at every dielectric interface (backing, gel): what the camera sees through the gel
(indenter, marker, housing). +inf where the ray leaves the scene. Traced with Mitsuba's ray queries on
an already loaded scene, at the recorded pixels' exact rays (lens distortion included)."""

from __future__ import annotations

import numpy as np


def depth_z(mi, mi_scene, origin: np.ndarray, directions_world: np.ndarray, R: np.ndarray, T: np.ndarray,
            max_interfaces: int = 12) -> np.ndarray:
    """z-depth (N,) in the camera frame x_cam = R x_world + T of the first non-dielectric surface hit by
    rays from ``origin`` along ``directions_world`` (N, 3)."""
    import drjit as dr

    n = len(directions_world)
    o = np.broadcast_to(np.asarray(origin, np.float32), (n, 3))
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(np.ascontiguousarray(o[:, i])) for i in range(3)]),
                   mi.Vector3f(*[mi.Float(np.ascontiguousarray(directions_world[:, i], np.float32)) for i in range(3)]))
    active = mi.Bool(True)
    hit_p = mi.Point3f(np.inf, np.inf, np.inf)
    ctx = mi.BSDFContext()
    for _ in range(max_interfaces):
        si = mi_scene.ray_intersect(ray, active)
        bsdf = si.bsdf(ray)
        clear = active & si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.DeltaTransmission)
        stop = active & si.is_valid() & ~clear
        hit_p = dr.select(stop, si.p, hit_p)
        bs, _ = bsdf.sample(ctx, si, mi.Float(0.99999), mi.Point2f(0.5, 0.5), clear)
        ray = dr.select(clear, si.spawn_ray(si.to_world(bs.wo)), ray)
        active = clear
        dr.eval(ray, active, hit_p)
        if not dr.any(active):
            break
    p = np.column_stack([np.array(hit_p.x), np.array(hit_p.y), np.array(hit_p.z)])
    z = np.full(n, np.inf)
    hit = np.isfinite(p).all(axis=1)
    z[hit] = p[hit] @ np.asarray(R, float)[2] + float(np.asarray(T, float)[2])
    return z


def write_depth_exr(path, depth: np.ndarray) -> None:
    """Write a depth map (H, W) in mm as a single-channel float32 EXR (channel ``Z``)."""
    import OpenEXR

    d = np.ascontiguousarray(depth, np.float32)
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, {"Z": d}) as f:
        f.write(str(path))


def read_depth_exr(path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        return np.array(f.channels()["Z"].pixels)
