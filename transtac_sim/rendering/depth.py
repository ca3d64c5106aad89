"""Depth AOV: for every recorded pixel, the z-depth (mm, in that camera's frame) of the first
non-transparent surface along the camera ray, the ray refracted (or, past the critical angle, reflected)
deterministically at every dielectric interface (backing, gel): what the camera sees through the gel
(indenter, marker, housing). +inf where the ray leaves the scene. Traced with Mitsuba's ray queries on
an already loaded scene, at the recorded pixels' exact rays (lens distortion included).

Contact: where the gel touches an indenter their surfaces coincide, and the ray spawned past the gel's
surface (offset by Mitsuba's epsilon) can start just inside the indenter and next hit its far side from
within. A hit on an indenter's inside (ray along its outward normal) therefore reports the gel surface the
ray last crossed: that is where the indenter's near face is."""

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
    last_interface_p = mi.Point3f(np.inf, np.inf, np.inf)
    indenters = [mi.ShapePtr(s) for s in mi_scene.shapes() if s.id().startswith("indenter")]
    ctx = mi.BSDFContext()
    for _ in range(max_interfaces):
        si = mi_scene.ray_intersect(ray, active)
        bsdf = si.bsdf(ray)
        clear = active & si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.DeltaTransmission)
        stop = active & si.is_valid() & ~clear
        on_indenter = mi.Bool(False)
        for ptr in indenters:
            on_indenter |= si.shape == ptr
        from_inside = on_indenter & (dr.dot(ray.d, si.n) > 0) & dr.isfinite(last_interface_p.x)
        hit_p = dr.select(stop, dr.select(from_inside, last_interface_p, si.p), hit_p)
        last_interface_p = dr.select(clear, si.p, last_interface_p)
        bs, _ = bsdf.sample(ctx, si, mi.Float(0.99999), mi.Point2f(0.5, 0.5), clear)
        ray = dr.select(clear, si.spawn_ray(si.to_world(bs.wo)), ray)
        active = clear
        dr.eval(ray, active, hit_p, last_interface_p)
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
