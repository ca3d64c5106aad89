"""Closed-form references for sphere indentation (mm, N, MPa).

Hertz (half-space, frictionless rigid sphere of radius R, depth d):
    F = 4/3 E/(1 - nu^2) sqrt(R) d^1.5
Bonded elastic layer of thickness h on a rigid base (Dimitriadis et al. 2002, Biophys. J. 82, eq. 12),
chi = sqrt(R d)/h, alpha0 = -1.2876 - 1.4678 nu + 1.3442 nu^2, beta0 = 0.6387 - 1.0277 nu + 1.5164 nu^2:
    F = F_Hertz [1 - 2 alpha0/pi chi + 4 alpha0^2/pi^2 chi^2 - 8/pi^3 (alpha0^3 + 4 pi^2/15 beta0) chi^3
                 + 16 alpha0/pi^4 (alpha0^3 + 3 pi^2/5 beta0) chi^4]
"""

from __future__ import annotations

import numpy as np


def hertz_force(young_mpa: float, poisson: float, radius_mm: float, depth_mm):
    return 4.0 / 3.0 * young_mpa / (1.0 - poisson**2) * np.sqrt(radius_mm) * np.asarray(depth_mm) ** 1.5


def bonded_layer_force(young_mpa: float, poisson: float, radius_mm: float, depth_mm, thickness_mm: float):
    chi = np.sqrt(radius_mm * np.asarray(depth_mm)) / thickness_mm
    a0 = -1.2876 - 1.4678 * poisson + 1.3442 * poisson**2
    b0 = 0.6387 - 1.0277 * poisson + 1.5164 * poisson**2
    pi = np.pi
    factor = (
        1.0
        - 2.0 * a0 / pi * chi
        + 4.0 * a0**2 / pi**2 * chi**2
        - 8.0 / pi**3 * (a0**3 + 4.0 * pi**2 / 15.0 * b0) * chi**3
        + 16.0 * a0 / pi**4 * (a0**3 + 3.0 * pi**2 / 5.0 * b0) * chi**4
    )
    return hertz_force(young_mpa, poisson, radius_mm, depth_mm) * factor
