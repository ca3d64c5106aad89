"""The renderer's inputs from the project's assembled ``Sensor`` (``transtac_sim.sensor.assembly``).

The sensor lives in the gel frame (origin at the centre of the bonded face); the renderer works in the
left camera's frame: x_left = x_gel + ``sensor.gel_origin_in_left_mm``. LED strips of radiant power P
over area A become Lambertian radiance L = P / (pi A) (mW / (mm^2 sr)); the pigment's emission spectrum
becomes a linear sRGB colour of unit luminance. The backing is a box covering the gel and the LED strips'
footprints (+1 mm); the housing an open box of the housing material around the cameras up to the backing.
"""

from __future__ import annotations

import numpy as np

from transtac_sim.rendering import geometry
from transtac_sim.rendering.inputs import (
    BackingSpec,
    CameraSpec,
    GelSpec,
    HousingSpec,
    IndenterSpec,
    LightSpec,
    MarkerSpec,
    Pigment,
    SensorScene,
)

_XYZ_TO_LINEAR_SRGB = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])


def _cie_xyz(wl_nm: np.ndarray) -> np.ndarray:
    """CIE 1931 colour matching functions, the multi-lobe Gaussian fit of Wyman, Sloan and Shirley (2013)."""
    def g(x, mu, s1, s2):
        return np.exp(-0.5 * ((x - mu) / np.where(x < mu, s1, s2)) ** 2)

    x = 1.056 * g(wl_nm, 599.8, 37.9, 31.0) + 0.362 * g(wl_nm, 442.0, 16.0, 26.7) - 0.065 * g(wl_nm, 501.1, 20.4, 26.2)
    y = 0.821 * g(wl_nm, 568.8, 46.9, 40.5) + 0.286 * g(wl_nm, 530.9, 16.3, 31.1)
    z = 1.217 * g(wl_nm, 437.0, 11.8, 36.0) + 0.681 * g(wl_nm, 459.0, 26.0, 13.8)
    return np.stack([x, y, z], axis=-1)


def spectrum_to_rgb(spectrum) -> np.ndarray:
    """Linear sRGB of a spectrum given as [wavelength_nm, value] pairs, clipped >= 0, luminance 1."""
    wl, val = np.asarray(spectrum, dtype=float).T
    grid = np.linspace(wl[0], wl[-1], 200)
    xyz = (np.interp(grid, wl, val)[:, None] * _cie_xyz(grid)).sum(axis=0)
    rgb = np.clip(_XYZ_TO_LINEAR_SRGB @ (xyz / xyz[1]), 0.0, None)
    return rgb / (0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2])


def scene_from_sensor(sensor, gel_vertices_gel: np.ndarray, gel_faces: np.ndarray,
                      indenters: list[tuple] = (),
                      ambient_white: float = 0.0) -> SensorScene:
    """``SensorScene`` of ``sensor`` with the gel's closed surface mesh (rest vertices in the gel frame) and
    indenters given as (vertices in the LEFT camera frame, faces, RGB) or (..., per-vertex albedo (V, 3))."""
    o = np.asarray(sensor.gel_origin_in_left_mm, float)
    hw = sensor.hardware
    cams = {n: CameraSpec(K=c.K, dist=np.asarray(c.dist, float), size=tuple(c.image_size), R=c.R, T=c.T, model=c.model)
            for n, c in sensor.cameras.items()}
    gel = GelSpec(np.asarray(gel_vertices_gel, float) + o, np.asarray(gel_faces), sensor.gel.refractive_index,
                  tuple(sensor.gel.absorption.visible_rgb_per_mm), sensor.gel.absorption.uv365_per_mm)
    lights, corners = [], [gel.vertices[:, :2]]
    for li in hw.lights:
        w, h = li.size_mm
        radiance = li.radiant_power_mw / (np.pi * w * h)
        spec = LightSpec(li.kind, np.asarray(li.center_mm, float) + o, np.asarray(li.normal, float), (w, h), radiance)
        lights.append(spec)
        corners.append(geometry.rectangle(spec.centre, spec.normal, spec.size, spec.u_axis)[0][:, :2])
    xy = np.concatenate(corners)
    t = hw.backing.thickness_mm
    lo = np.array([*(xy.min(axis=0) - 1.0), o[2] - t])
    hi = np.array([*(xy.max(axis=0) + 1.0), o[2]])
    backing = BackingSpec(lo, hi, sensor.backing.refractive_index, sensor.backing.absorption.uv365_per_mm)
    centres = np.array([c.centre for c in cams.values()])
    wall = hw.housing.wall_mm
    h_lo = np.array([min(lo[0], centres[:, 0].min()) - wall, min(lo[1], centres[:, 1].min()) - wall, centres[:, 2].min() - 4.0])
    h_hi = np.array([max(hi[0], centres[:, 0].max()) + wall, max(hi[1], centres[:, 1].max()) + wall, lo[2] - 0.05])
    housing = HousingSpec([geometry.open_box(h_lo, h_hi)], float(np.mean(sensor.housing.reflectance_rgb)))
    p = sensor.pigment
    pigment = Pigment(tuple(p.white_light_rgb), p.white_light_opacity, p.uv365_absorptance, p.quantum_yield,
                      tuple(spectrum_to_rgb(p.emission_spectrum)))
    markers = MarkerSpec(np.asarray(sensor.markers_rest_gel_mm, float) + o, sensor.marker_radius_mm, pigment)
    leaks = [li.visible_leak for li in hw.lights if li.kind == "uv"]
    return SensorScene(cams, gel, backing, housing, markers, lights,
                       [IndenterSpec(np.asarray(t[0], float), np.asarray(t[1]), tuple(t[2]), t[3] if len(t) > 3 else None)
                        for t in indenters],
                       uv_visible_leak=float(np.mean(leaks)) if leaks else 0.0, ambient_white=ambient_white)
