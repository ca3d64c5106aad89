"""Closed-form references for sphere indentation (mm, N, MPa).

Hertz (half-space, frictionless rigid sphere of radius R, depth d):
    F = 4/3 E/(1 - nu^2) sqrt(R) d^1.5
Bonded elastic layer of thickness h on a rigid base (Dimitriadis et al. 2002, Biophys. J. 82, eq. 12 with
the coefficients for a sample bonded to the substrate), chi = sqrt(R d)/h,
    alpha0 = -(1.2876 - 1.4678 nu + 1.3442 nu^2) / (1 - nu),  beta0 = (0.6387 - 1.0277 nu + 1.5164 nu^2) / (1 - nu):
    F = F_Hertz [1 - 2 alpha0/pi chi + 4 alpha0^2/pi^2 chi^2 - 8/pi^3 (alpha0^3 + 4 pi^2/15 beta0) chi^3
                 + 16 alpha0/pi^4 (alpha0^3 + 3 pi^2/5 beta0) chi^4]
At nu = 0.5 (alpha0 = -1.7795, beta0 = 1.0079) the bracket is 1 + 1.133 chi + 1.283 chi^2 + 0.769 chi^3
- 0.0975 chi^4. This incompressible series is usually quoted with + 0.0975 chi^4 as its last term, but the
general formula gives - 0.0975, and the same formula reproduces every coefficient of the paper's non-bonded
series (1 + 0.884 chi + 0.781 chi^2 + 0.386 chi^3 + 0.0048 chi^4) with their signs
(tests/test_physics_analytic.py). The two signs differ by 0.195 chi^4, 0.13 % of F at chi = 0.32.
"""

from __future__ import annotations

import numpy as np


def hertz_force(young_mpa: float, poisson: float, radius_mm: float, depth_mm):
    return 4.0 / 3.0 * young_mpa / (1.0 - poisson**2) * np.sqrt(radius_mm) * np.asarray(depth_mm) ** 1.5


def layer_factor(alpha0: float, beta0: float, chi):
    """The bracket of the module docstring: F / F_Hertz for a layer with coefficients alpha0, beta0."""
    chi = np.asarray(chi, dtype=np.float64)
    a0, b0, pi = alpha0, beta0, np.pi
    return (
        1.0
        - 2.0 * a0 / pi * chi
        + 4.0 * a0**2 / pi**2 * chi**2
        - 8.0 / pi**3 * (a0**3 + 4.0 * pi**2 / 15.0 * b0) * chi**3
        + 16.0 * a0 / pi**4 * (a0**3 + 3.0 * pi**2 / 5.0 * b0) * chi**4
    )


def bonded_coefficients(poisson: float) -> tuple[float, float]:
    """(alpha0, beta0) of Dimitriadis et al. (2002) for a layer bonded to its rigid base."""
    alpha0 = -(1.2876 - 1.4678 * poisson + 1.3442 * poisson**2) / (1.0 - poisson)
    beta0 = (0.6387 - 1.0277 * poisson + 1.5164 * poisson**2) / (1.0 - poisson)
    return alpha0, beta0


def bonded_layer_force(young_mpa: float, poisson: float, radius_mm: float, depth_mm, thickness_mm: float):
    chi = np.sqrt(radius_mm * np.asarray(depth_mm)) / thickness_mm
    return hertz_force(young_mpa, poisson, radius_mm, depth_mm) * layer_factor(*bonded_coefficients(poisson), chi)
