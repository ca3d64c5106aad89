"""A representative TransTac sensor built from plain numbers, shared by tests and scripts (left camera
frame, mm): gel 32 x 24 x 5 (x right, y down) with its bonded face at z = 17 and contact face at z = 22,
acrylic backing z in [15, 17] (36 x 37 mm), cameras 12 mm apart (right camera at x = +12: T = (-12, 0, 0)),
640 x 480 with 100 deg horizontal field of view and mild barrel distortion, markers of radius 0.25 mm
0.5 mm below the contact face on a jittered 2.5 mm grid, UV and white LED strips along the two long
edges just in front of the backing (out of view), tilted 30 deg towards the gel's centre; an open matte
black housing.
"""

from __future__ import annotations

import numpy as np
import trimesh

from transtac_sim.rendering import geometry
from transtac_sim.rendering.inputs import (
    BackingSpec,
    CameraSpec,
    FrameState,
    GelSpec,
    HousingSpec,
    IndenterSpec,
    LightSpec,
    MarkerSpec,
    Pigment,
    SensorScene,
)

GEL_LO, GEL_HI = np.array([-16.0, -12.0, 17.0]), np.array([16.0, 12.0, 22.0])
BACKING_LO, BACKING_HI = np.array([-18.0, -18.5, 15.0]), np.array([18.0, 18.5, 17.0])


def camera(size=(640, 480), hfov_deg: float = 100.0, dist=(-0.03, 0.005, 0.0, 0.0, 0.0), T=(0.0, 0.0, 0.0)) -> CameraSpec:
    w, h = size
    f = (w / 2) / np.tan(np.radians(hfov_deg) / 2)
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return CameraSpec(K=K, dist=np.asarray(dist, float), size=(w, h), R=np.eye(3), T=np.asarray(T, float))


def stereo_cameras(size=(640, 480), dist=(-0.03, 0.005, 0.0, 0.0, 0.0)) -> dict[str, CameraSpec]:
    return {"left": camera(size, dist=dist), "right": camera(size, dist=dist, T=(-12.0, 0.0, 0.0))}


def gel_mesh(spacing_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Closed box surface of the gel, triangles about ``spacing_mm`` across (outward normals)."""
    box = trimesh.creation.box(extents=GEL_HI - GEL_LO)
    box.apply_translation((GEL_LO + GEL_HI) / 2)
    box = box.subdivide_to_size(spacing_mm)
    return np.asarray(box.vertices), np.asarray(box.faces)


def marker_grid(spacing_mm: float = 2.5, depth_mm: float = 0.5, jitter_mm: float = 0.5, margin_mm: float = 1.0,
                seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xs = np.arange(GEL_LO[0] + margin_mm, GEL_HI[0] - margin_mm + 1e-9, spacing_mm)
    ys = np.arange(GEL_LO[1] + margin_mm, GEL_HI[1] - margin_mm + 1e-9, spacing_mm)
    x, y = (a.ravel() for a in np.meshgrid(xs - (xs.mean()), ys - ys.mean()))
    xy = np.column_stack([x, y]) + rng.uniform(-jitter_mm, jitter_mm, (len(x), 2))
    return np.column_stack([xy, np.full(len(x), GEL_HI[2] - depth_mm)])


def led_strips(uv_radiance: float = 300.0, white_radiance: float = 60.0) -> list[LightSpec]:
    lights = []
    for sign in (-1.0, 1.0):  # y = -16.5 (top of the image) and y = +16.5 (bottom), out of the cameras' view
        normal = np.array([0.0, -sign * np.sin(np.radians(30)), np.cos(np.radians(30))])
        lights.append(LightSpec("uv", np.array([0.0, 16.5 * sign, 14.9]), normal, (24.0, 1.2), uv_radiance))
        lights.append(LightSpec("white", np.array([0.0, 17.7 * sign, 14.9]), normal, (24.0, 1.2), white_radiance))
    return lights


def housing() -> HousingSpec:
    return HousingSpec([geometry.open_box([-24.0, -22.0, -4.0], [36.0, 22.0, 14.95])])


def sensor_scene(size=(640, 480), markers: np.ndarray | None = None, radius: float = 0.25,
                 dist=(-0.03, 0.005, 0.0, 0.0, 0.0), gel_spacing_mm: float = 1.0, ambient_white: float = 0.05,
                 indenters: list[IndenterSpec] | None = None, pigment: Pigment | None = None) -> SensorScene:
    v, f = gel_mesh(gel_spacing_mm)
    return SensorScene(
        cameras=stereo_cameras(size, dist), gel=GelSpec(v, f), backing=BackingSpec(BACKING_LO, BACKING_HI),
        housing=housing(), markers=MarkerSpec(marker_grid() if markers is None else np.asarray(markers, float), radius,
                                              pigment or Pigment()),
        lights=led_strips(), indenters=indenters or [], ambient_white=ambient_white)


def dimple(points: np.ndarray, depth_mm: float, centre_xy=(0.0, 0.0), sigma_mm: float = 2.5,
           only_contact_face: bool = True) -> np.ndarray:
    """Points pushed towards the cameras by a Gaussian dimple depth * exp(-r^2 / (2 sigma^2)) (a stand-in
    for an FEM solution of an indentation); with ``only_contact_face`` only points on z = 22 move."""
    p = np.array(points, float)
    r2 = ((p[:, :2] - centre_xy) ** 2).sum(axis=1)
    move = np.isclose(p[:, 2], GEL_HI[2]) if only_contact_face else np.ones(len(p), bool)
    p[move, 2] -= depth_mm * np.exp(-r2[move] / (2 * sigma_mm**2))
    return p


def indented_frame(scene: SensorScene, depth_mm: float, centre_xy=(0.0, 0.0), sigma_mm: float = 2.5) -> FrameState:
    """Gel surface and markers under a Gaussian dimple (markers follow the surface above them); an indenter
    (if the scene has one, a sphere from ``indenter_sphere``) is moved to touch the dimple's lowest point."""
    gel = dimple(scene.gel.vertices, depth_mm, centre_xy, sigma_mm)
    markers = dimple(scene.markers.centres, depth_mm, centre_xy, sigma_mm, only_contact_face=False)
    ind = []
    for spec in scene.indenters:
        v = np.asarray(spec.vertices, float)
        lowest = v[:, 2].min()
        shift = np.array([centre_xy[0] - v[:, 0].mean(), centre_xy[1] - v[:, 1].mean(), GEL_HI[2] - depth_mm - lowest])
        ind.append(v + shift)
    return FrameState(gel_vertices=gel, marker_centres=markers, indenter_vertices=ind or None)


def indenter_sphere(radius_mm: float = 4.0, rgb=(0.8, 0.25, 0.1)) -> IndenterSpec:
    """A sphere resting on the undeformed contact face at (0, 0)."""
    m = trimesh.creation.icosphere(subdivisions=3, radius=radius_mm)
    return IndenterSpec(np.asarray(m.vertices) + [0.0, 0.0, GEL_HI[2] + radius_mm], np.asarray(m.faces), rgb)
