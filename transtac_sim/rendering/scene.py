"""The sensor as a Mitsuba 3 scene for one illumination, built once and updated in place per frame.

World frame: the left camera's OpenCV frame (mm). Every interface is a ``dielectric`` BSDF carrying the
index ratio across it (Mitsuba's "interior" is the side opposite the normal):
- ``backing``: its outer face, sides and the part of its gel-side face not under the gel, acrylic | air;
- ``bond``: the gel's bonded faces (planar, static), gel | acrylic, normals towards the backing;
- ``gel``: every other gel face, gel | air; its vertex buffer is replaced every frame (``mi.traverse``);
- ``markers``: one mesh of small icospheres (optionally ellipsoids), moved every frame. Under UV they
  are Lambertian area emitters inside the gel with per-marker radiance (a per-vertex attribute, see
  ``illumination``); under white light they are pale semi-transparent diffuse bodies (``mask``) that
  also emit the white LED light they reflect (baked, see ``illumination``);
- ``indenter_i``: diffuse in its colour, moved every frame; under white light it also emits the LED
  light it reflects (baked per vertex); ``housing_i``: matte black, two-sided;
- LED strips: under UV light the UV strips are one-sided rectangular area lights emitting their small
  visible leak. The white strips are not emitters: the light they send through the backing and gel onto
  markers and indenters is baked into those (``illumination``), because a path tracer cannot connect it
  (no shadow ray crosses a dielectric). White light adds the room's ambient light if set.
Absorption in the gel and backing at visible wavelengths (~1 % over 5 mm) is left out of the renders;
at 365 nm it is in the markers' excitation (``illumination``).
"""

from __future__ import annotations

import numpy as np
import trimesh

from transtac_sim.rendering import geometry
from transtac_sim.rendering.illumination import fluorescence_radiance, lambertian_radiance, led_irradiance
from transtac_sim.rendering.inputs import FrameState, SensorScene

MARKER_SUBDIVISIONS = 2


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, np.float32).ravel())


def make_mesh(mi, name: str, vertices, faces, bsdf: dict, emitter: dict | None = None,
              attributes: dict[str, np.ndarray] | None = None):
    """A Mitsuba mesh from numpy arrays (vertex normals left out: flat shading)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    if emitter is not None:
        props["emitter"] = mi.load_dict(emitter)
    m = mi.Mesh(name, len(vertices), len(faces), props=props, has_vertex_normals=False)
    for key, val in (attributes or {}).items():
        m.add_attribute(key, val.shape[1], mi.Float(_f32(val)))
    p = mi.traverse(m)
    p["vertex_positions"] = mi.Float(_f32(vertices))
    p["faces"] = mi.UInt32(np.asarray(faces, np.uint32).ravel())
    p.update()
    return m


def _dielectric(n_int: float, n_ext: float) -> dict:
    return {"type": "dielectric", "int_ior": float(n_int), "ext_ior": float(n_ext)}


def _diffuse(rgb, twosided: bool = False) -> dict:
    d = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(c) for c in rgb]}}
    return {"type": "twosided", "bsdf": d} if twosided else d


def backing_faces(scene: SensorScene) -> tuple[np.ndarray, np.ndarray]:
    """The backing box's faces less the part of its gel-side face covered by the gel (whose footprint,
    the bonded face's bounding rectangle, must lie within the backing's)."""
    b, g = scene.backing, scene.gel
    lo, hi = np.asarray(b.lo, float), np.asarray(b.hi, float)
    v, f = geometry.box_mesh(lo, hi)
    tri = v[f]
    top = np.all(np.isclose(tri[:, :, 2], hi[2]), axis=1)
    gv = np.asarray(g.vertices, float)
    bv = gv[np.unique(g.faces[geometry.bonded_faces(gv, g.faces)])]
    glo, ghi = bv[:, :2].min(axis=0), bv[:, :2].max(axis=0)
    if not np.isclose(g.bonded_z, hi[2]) or np.any(glo < lo[:2] - 1e-6) or np.any(ghi > hi[:2] + 1e-6):
        raise ValueError("the gel's bonded face must lie on the backing's face z = hi[2], within its footprint")
    # ring between the backing's rectangle (outer) and the gel's footprint (inner), normals +z
    xs, ys = [lo[0], glo[0], ghi[0], hi[0]], [lo[1], glo[1], ghi[1], hi[1]]
    ring_v, ring_f = [], []
    for i in range(3):
        for j in range(3):
            if (i, j) == (1, 1) or xs[i + 1] - xs[i] < 1e-9 or ys[j + 1] - ys[j] < 1e-9:
                continue
            k = len(ring_v)
            ring_v += [[xs[i], ys[j], hi[2]], [xs[i + 1], ys[j], hi[2]], [xs[i + 1], ys[j + 1], hi[2]], [xs[i], ys[j + 1], hi[2]]]
            ring_f += [[k, k + 1, k + 2], [k, k + 2, k + 3]]
    ring_f = np.array(ring_f, int).reshape(-1, 3)
    return np.vstack([v, np.array(ring_v).reshape(-1, 3)]), np.vstack([f[~top], ring_f + len(v)])


class SceneAssembly:
    """One illumination's Mitsuba scene (``kind`` in {"uv", "white", "geometry"}; "geometry" has no
    lights, for AOVs only). ``update(frame)`` moves the gel, markers and indenters in place."""

    def __init__(self, mi, scene: SensorScene, kind: str, max_depth: int = 8, rr_depth: int = 5):
        self.mi, self.scene, self.kind = mi, scene, kind
        g, mk = scene.gel, scene.markers
        self.bonded = geometry.bonded_faces(g.vertices, g.faces)
        self.template_v, template_f = geometry.unit_sphere(MARKER_SUBDIVISIONS)
        self.centres = np.asarray(mk.centres, float)
        self.deformation = mk.deformation
        self.gel_vertices = np.asarray(g.vertices, float)
        n_m = len(self.centres)
        d = {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth), "rr_depth": int(rr_depth)}}
        bv, bf = backing_faces(scene)
        d["backing"] = make_mesh(mi, "backing", bv, bf, _dielectric(scene.backing.ior, 1.0))
        d["bond"] = make_mesh(mi, "bond", g.vertices, g.faces[self.bonded], _dielectric(g.ior, scene.backing.ior))
        d["gel"] = make_mesh(mi, "gel", g.vertices, g.faces[~self.bonded], _dielectric(g.ior, 1.0))
        mv = geometry.marker_vertices(self.template_v, self.centres, mk.radius, self.deformation)
        mf = geometry.tile_faces(template_f, len(self.template_v), n_m)
        pig = mk.pigment
        baked = {"type": "area", "radiance": {"type": "mesh_attribute", "name": "vertex_color"}}
        if kind == "uv":
            d["markers"] = make_mesh(mi, "markers", mv, mf, _diffuse(np.asarray(pig.white_rgb) * pig.white_opacity),
                                     baked, {"vertex_color": self._marker_colours()})
        elif kind == "white":
            d["markers"] = make_mesh(mi, "markers", mv, mf, {"type": "mask", "opacity": float(pig.white_opacity),
                                                              "bsdf": _diffuse(pig.white_rgb)},
                                     baked, {"vertex_color": self._marker_colours()})
        else:
            d["markers"] = make_mesh(mi, "markers", mv, mf, _diffuse(pig.white_rgb))
        self.indenter_vertices = [np.asarray(ind.vertices, float) for ind in scene.indenters]
        for i, ind in enumerate(scene.indenters):
            if kind == "white":
                d[f"indenter_{i}"] = make_mesh(mi, f"indenter_{i}", ind.vertices, ind.faces, _diffuse(ind.rgb),
                                               baked, {"vertex_color": self._indenter_colours(i)})
            else:
                d[f"indenter_{i}"] = make_mesh(mi, f"indenter_{i}", ind.vertices, ind.faces, _diffuse(ind.rgb))
        for i, (hv, hf) in enumerate(scene.housing.meshes):
            d[f"housing_{i}"] = make_mesh(mi, f"housing_{i}", hv, hf, _diffuse([scene.housing.reflectance] * 3, True))
        for i, light in enumerate(scene.lights):  # white strips' light is baked (see the module doc)
            radiance = scene.uv_visible_leak * light.radiance if kind == light.kind == "uv" else 0.0
            if radiance > 0:
                lv, lf = geometry.rectangle(light.centre, light.normal, light.size, light.u_axis)
                d[f"light_{i}"] = make_mesh(mi, f"light_{i}", lv, lf, _diffuse([0.0] * 3),
                                            {"type": "area", "radiance": {"type": "rgb", "value": [float(radiance)] * 3}})
        if kind == "white" and scene.ambient_white > 0:
            d["ambient"] = {"type": "constant", "radiance": {"type": "rgb", "value": [float(scene.ambient_white)] * 3}}
        self.mi_scene = mi.load_dict(d)
        self.params = mi.traverse(self.mi_scene)

    def _irradiance(self, points: np.ndarray, normals: np.ndarray | None = None, samples=(24, 4)) -> np.ndarray:
        """Irradiance from this illumination's LED strips (``illumination.led_irradiance``, ``samples`` points
        along x across each strip)."""
        s, gv = self.scene, self.gel_vertices
        mu_gel = s.gel.absorption_uv_per_mm if self.kind == "uv" else float(np.mean(s.gel.absorption_rgb_per_mm))
        mu_back = s.backing.absorption_uv_per_mm if self.kind == "uv" else 0.0
        return led_irradiance(points, s.lights, self.kind, (gv.min(axis=0), gv.max(axis=0)), mu_gel,
                              (np.asarray(s.backing.lo, float), np.asarray(s.backing.hi, float)), mu_back, normals, samples)

    def _marker_colours(self) -> np.ndarray:
        """Per-vertex emitted radiance (K * Vt, 3) of the markers at their current positions."""
        E = self._irradiance(self.centres)
        pig = self.scene.markers.pigment
        if self.kind == "uv":
            rad = fluorescence_radiance(E, pig)
        else:
            rad = lambertian_radiance(E, np.asarray(pig.white_rgb) * pig.white_opacity)
        return np.repeat(rad, len(self.template_v), axis=0)

    def _indenter_colours(self, i: int) -> np.ndarray:
        """Per-vertex radiance (V, 3) of indenter ``i`` reflecting the white LEDs."""
        v = self.indenter_vertices[i]
        normals = trimesh.Trimesh(v, self.scene.indenters[i].faces, process=False).vertex_normals
        spec = self.scene.indenters[i]
        albedo = spec.rgb if spec.albedo is None else spec.albedo
        return lambertian_radiance(self._irradiance(v, np.asarray(normals), samples=(8, 2)), albedo)

    def update(self, frame: FrameState) -> None:
        """Move the deformable parts to ``frame`` (vertex buffers only; topology never changes)."""
        mi, p = self.mi, self.params
        if frame.gel_vertices is not None:
            self.gel_vertices = np.asarray(frame.gel_vertices, float)
            p["gel.vertex_positions"] = mi.Float(_f32(self.gel_vertices))
        if frame.marker_centres is not None or frame.marker_deformation is not None:
            if frame.marker_centres is not None:
                self.centres = np.asarray(frame.marker_centres, float)
            if frame.marker_deformation is not None:
                self.deformation = frame.marker_deformation
            mv = geometry.marker_vertices(self.template_v, self.centres, self.scene.markers.radius, self.deformation)
            p["markers.vertex_positions"] = mi.Float(_f32(mv))
        if self.kind != "geometry" and (frame.marker_centres is not None or frame.gel_vertices is not None):
            p["markers.vertex_color"] = mi.Float(_f32(self._marker_colours()))
        for i, v in enumerate(frame.indenter_vertices or []):
            self.indenter_vertices[i] = np.asarray(v, float)
            p[f"indenter_{i}.vertex_positions"] = mi.Float(_f32(v))
            if self.kind == "white":
                p[f"indenter_{i}.vertex_color"] = mi.Float(_f32(self._indenter_colours(i)))
        p.update()
