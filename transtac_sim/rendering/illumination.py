"""LED light reaching surfaces inside and beyond the gel, baked into emission for the render.

Why: the LEDs sit behind the backing, so light reaching a marker (inside the gel) or an indenter (beyond
it) has crossed specular dielectric interfaces; a path tracer can only find such light by chance (no
shadow ray passes a dielectric), which makes noisy images. The camera side of the path (camera ->
backing -> gel -> surface) is specular only and is rendered exactly; the light side is computed here:

1. Irradiance from the LED strips of one kind, each a one-sided Lambertian rectangle of radiance L,
   summed over a grid of points on the strip: E = sum L cos(theta_led) [cos(theta_recv)] dA / d^2
   * exp(-(mu_gel l_gel + mu_backing l_backing)), where l_gel and l_backing are the lengths of the
   straight segment LED -> point inside the gel's bounding box and the backing box (Beer-Lambert).
   Scalar irradiance (fluence rate, no receiver cosine) for the markers, planar irradiance with the
   receiver's normal for indenter vertices. Neglected: refraction and Fresnel losses on the way in (they
   bend the paths by a few degrees and change E by a few per cent, smoothly), shadowing by markers or
   indenters, light reflected inside the gel or by the housing.
2. UV: a marker absorbs E * pi r^2 * absorptance of UV and re-emits quantum_yield of it (counted in power,
   the Stokes shift's energy loss folded into the yield) uniformly over its surface 4 pi r^2, as a
   Lambertian emitter: radiance L_m = E * absorptance * quantum_yield / (4 pi), in the pigment's emission
   colour. The renderer makes the markers area emitters inside the dielectric gel with that radiance.
3. White light: a diffuse indenter of albedo rho reflects L = rho E / pi; a marker, opacity * its
   colour * E / pi. Both become area emitters (per-vertex radiance) in the white-light scene, on top of
   their BSDFs (which still see the room's ambient light and interreflections).
Units: the LED's radiance unit per mm^2 sr, so E and L_m in the same arbitrary linear units.
"""

from __future__ import annotations

import numpy as np

from transtac_sim.rendering.geometry import rectangle
from transtac_sim.rendering.inputs import LightSpec, Pigment


def segment_length_in_box(p: np.ndarray, q: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Length of each segment p -> q (broadcast (..., 3)) inside the box [lo, hi] (slab method)."""
    d = q - p
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - p) / d, (hi - p) / d
    inside_slab = (p >= lo) & (p <= hi)
    tmin = np.where(d == 0, np.where(inside_slab, -np.inf, np.inf), np.minimum(t0, t1))
    tmax = np.where(d == 0, np.where(inside_slab, np.inf, -np.inf), np.maximum(t0, t1))
    a, b = np.clip(tmin.max(axis=-1), 0.0, 1.0), np.clip(tmax.min(axis=-1), 0.0, 1.0)
    return np.maximum(b - a, 0.0) * np.linalg.norm(d, axis=-1)


def led_irradiance(points: np.ndarray, lights: list[LightSpec], kind: str, gel_box: tuple[np.ndarray, np.ndarray],
                   mu_gel: float, backing_box: tuple[np.ndarray, np.ndarray], mu_backing: float,
                   normals: np.ndarray | None = None, samples: tuple[int, int] = (24, 4)) -> np.ndarray:
    """Irradiance (K,) at ``points`` (K, 3) from the strips of ``kind`` among ``lights`` (left frame, mm;
    absorption coefficients in 1/mm): scalar, or planar about unit ``normals`` (K, 3) when given."""
    P = np.atleast_2d(np.asarray(points, float))
    E = np.zeros(len(P))
    for light in (li for li in lights if li.kind == kind):
        corners, _ = rectangle(light.centre, light.normal, light.size, light.u_axis)
        u, w = corners[1] - corners[0], corners[3] - corners[0]
        su, sw = (np.arange(samples[0]) + 0.5) / samples[0], (np.arange(samples[1]) + 0.5) / samples[1]
        pts = (corners[0] + su[:, None, None] * u + sw[None, :, None] * w).reshape(-1, 3)
        n = np.asarray(light.normal, float) / np.linalg.norm(light.normal)
        dA = light.size[0] * light.size[1] / len(pts)
        d = P[:, None, :] - pts[None]
        r2 = (d**2).sum(axis=-1)
        cos_led = np.clip(d @ n / np.sqrt(r2), 0.0, None)
        if normals is not None:
            cos_led = cos_led * np.clip(-np.einsum("ksi,ki->ks", d, normals) / np.sqrt(r2), 0.0, None)
        tau = np.zeros_like(r2)
        for mu, box in ((mu_gel, gel_box), (mu_backing, backing_box)):
            if mu > 0:
                tau += mu * segment_length_in_box(pts[None], P[:, None], *box)
        E += (light.radiance * cos_led * dA / r2 * np.exp(-tau)).sum(axis=1)
    return E


def fluorescence_radiance(E: np.ndarray, pigment: Pigment) -> np.ndarray:
    """Linear RGB radiance (K, 3) of markers under UV irradiance ``E`` (K,)."""
    scale = np.asarray(E, float) * pigment.uv_absorptance * pigment.quantum_yield / (4 * np.pi)
    return scale[:, None] * np.asarray(pigment.emission_rgb, float)[None]


def lambertian_radiance(E: np.ndarray, rgb) -> np.ndarray:
    """Linear RGB radiance (K, 3) reflected by Lambertian surfaces of albedo ``rgb`` ((3,), or (K, 3) per
    surface point) under irradiance ``E`` (K,)."""
    return np.asarray(E, float)[:, None] * np.asarray(rgb, float).reshape(-1, 3) / np.pi
